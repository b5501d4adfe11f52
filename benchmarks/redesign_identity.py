"""Same seeds, same bytes: renders of every preset and the figures of ``scopetwin run`` / ``study thesis``.

A restructuring must not change behaviour. This script drives the command line only (the
contract, docs/contract.md), so it survives any internal restructuring:

* every Part I preset rendered with Mitsuba (``scopetwin render PRESET --spp 4 --seed 1``),
* a GRIN target image (``optics grin thesis-8.3.2-grin-realized --image dots-25``) and the four CMU Siemens-star
  channels (``optics cmu --out``),
* the JSON figures of ``scopetwin run`` and ``scopetwin study thesis`` (timings and paths dropped).

Images are compared by the SHA-256 of their float32 pixel data (EXR headers carry versions and are ignored), figures
exactly.  Usage::

    python benchmarks/redesign_identity.py --record benchmarks/redesign_identity.json   # before a change
    python benchmarks/redesign_identity.py --check benchmarks/redesign_identity.json    # after it (exit 1 on a diff)
    python benchmarks/redesign_identity.py --check ... --quick                          # renders only (~1 min)

The recorded file holds figures of this machine's Mitsuba/LLVM build; re-record it when those versions change or a
change of behaviour is intended (last: the posterior's coarse-to-fine evidence search, which moved the run / thesis
figures by nanometres — the record had already drifted by 243 figures since the truth-levelling fix, through later
reconstruction changes; the redesign itself had been checked identical against the first record).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

PART_I_PRESETS = (
    "thesis-1.10-deflectometry",
    "thesis-2.8.1-perpendicular",
    "thesis-2.8.1-angular",
    "thesis-2.8.3-substrate",
    "thesis-2.8.3-mirror",
    "thesis-2.8.5-distortion",
    "thesis-2.9.1-target-6x4",
    "thesis-2.9.1-target-4x4",
)
# keys whose values legitimately differ between two runs of the same seeds
_VOLATILE = {
    "seconds",
    "timings_s",
    "report",
    "results",
    "plots",
    "image",
    "truth",
    "surface_path",
    "heights",
    "where",
    "out",
}


def _scopetwin(*args: str, ok: tuple[int, ...] = (0,)) -> None:
    """Run a ``scopetwin`` command; an exit status outside ``ok`` is an error."""
    exe = Path(sys.executable).with_name("scopetwin")
    done = subprocess.run([str(exe), *args], stdout=subprocess.DEVNULL)
    if done.returncode not in ok:
        raise subprocess.CalledProcessError(done.returncode, [str(exe), *args])


def _pixels_sha(path: Path) -> str:
    with OpenEXR.File(str(path)) as f:
        digest = hashlib.sha256()
        for name, channel in sorted(f.channels().items()):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(channel.pixels, dtype=np.float32).tobytes())
    return digest.hexdigest()


def _figures(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _figures(v) for k, v in value.items() if k not in _VOLATILE and "seconds" not in k}
    if isinstance(value, list):
        return [_figures(v) for v in value]
    return value


def measure(quick: bool) -> dict[str, Any]:
    out: dict[str, Any] = {"renders": {}, "figures": {}}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for preset in PART_I_PRESETS:
            _scopetwin("render", preset, "--out", str(tmp / preset), "--spp", "4", "--seed", "1")
            out["renders"][preset] = _pixels_sha(tmp / preset / "image.exr")
            print(f"  {preset}: {out['renders'][preset][:16]}", flush=True)
        _scopetwin(
            "optics",
            "grin",
            "thesis-8.3.2-grin-realized",
            "--image",
            "dots-25",
            "--out",
            str(tmp / "grin.exr"),
            "--spp",
            "4",
            "--seed",
            "1",
        )
        out["renders"]["grin-dots-25"] = _pixels_sha(tmp / "grin.exr")
        _scopetwin("optics", "cmu", "--out", str(tmp / "cmu"), "--spp", "4", "--no-cells")
        for exr in sorted((tmp / "cmu").glob("*.exr")):
            out["renders"][f"cmu-{exr.stem}"] = _pixels_sha(exr)
        print("  grin and cmu images done", flush=True)
        if quick:
            return out
        _scopetwin("run", "--out", str(tmp / "run"), "--json", str(tmp / "run.json"), "--quiet")
        out["figures"]["run"] = _figures(json.loads((tmp / "run.json").read_text()))
        # exit 1: some task failed; the report and results.json list it, and the comparison shows which
        _scopetwin("study", "thesis", "--workers", "0", "--quiet", "--out", str(tmp / "study"), ok=(0, 1))
        out["figures"]["study-thesis"] = _figures(json.loads((tmp / "study" / "results.json").read_text()))
    return out


def _diff(a: Any, b: Any, where: str, found: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                found.append(f"{where}.{k}: only in {'recorded' if k in a else 'now'}")
            else:
                _diff(a[k], b[k], f"{where}.{k}", found)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _diff(x, y, f"{where}[{i}]", found)
    elif a != b:
        found.append(f"{where}: recorded {a!r}, now {b!r}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--record", type=Path, help="write the figures to this JSON file")
    group.add_argument("--check", type=Path, help="compare with the figures recorded in this JSON file")
    ap.add_argument("--quick", action="store_true", help="renders only (skip run and study thesis)")
    args = ap.parse_args()
    now = measure(args.quick)
    if args.record:
        args.record.write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")
        print(f"recorded {len(now['renders'])} renders and {len(now['figures'])} figure sets -> {args.record}")
        return 0
    recorded = json.loads(args.check.read_text())
    recorded["figures"] = {} if args.quick else _figures(recorded["figures"])
    found: list[str] = []
    _diff(recorded, now, "", found)
    for line in found:
        print("DIFF", line)
    print(
        f"{len(now['renders'])} renders, {len(now['figures'])} figure sets: "
        f"{'identical' if not found else f'{len(found)} differences'}"
    )
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
