"""The dataset folder: atomic sample writes, the manifest, recovery after a kill, generation and verification.

See :mod:`scopetwin.sim.datasets` for the layout. A sample folder is staged under a temporary name in ``DIR/samples``
and
renamed into place when complete (:class:`scopetwin.sim.measurement.StagedOutput`); ``resume`` removes temporary
folders,
re-lists finished samples the manifest lost (a killed client) and renders only what is missing; ``verify`` checks
every sample against the manifest and its own hashes.

A dataset folder may come from someone else, so ``verify`` and ``resume`` read its files through
:mod:`scopetwin.scenes.safe_read`: a sample's files must be regular files inside its folder (a name with ``..``, an
absolute name, a link out of the folder, a FIFO or a device make the sample corrupt, with the reason, and nothing
is opened through them), JSON files are read under a size limit with bounded nesting, and a sample folder that is a
symbolic link is corrupt (``resume`` removes the link, never what it points to).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import socket
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.inputs import InputError, parse_json, read_text_input
from scopetwin.scenes.io import open_append
from scopetwin.scenes.safe_read import check_format, check_regular, read_json_inside, resolve_inside
from scopetwin.sim.datasets.config import SAMPLE_PACKAGES, DatasetError
from scopetwin.sim.datasets.lock import DatasetBusy, DatasetLock, holder
from scopetwin.sim.datasets.plan import READABLE_FORMATS, Plan
from scopetwin.sim.datasets.runner import check_scheduler, dask_client, failure_text, init_worker, run_tasks
from scopetwin.sim.measurement import StagedOutput, _refuse_link, remove_stale_stage, versions

CONFIG_FILE = "dataset.json"
MANIFEST = "manifest.jsonl"
SAMPLES = "samples"
TMP_PREFIX = ".tmp-"
SAMPLE_FILE = "sample.json"
#: Largest manifest read, bytes (a line is about 600 bytes: over a million samples).
MANIFEST_LIMIT = 1024 * 2**20
#: Largest file of a sample whose hash is checked, bytes (the EXR limit of :data:`scopetwin.scenes.inputs.LIMITS`).
SAMPLE_FILE_LIMIT = 4096 * 2**20

log = logging.getLogger(__name__)


def sha256_file(path: Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sample_name(index: int) -> str:
    """The folder name of sample ``index`` (six digits)."""
    return f"{index:06d}"


def _sample_record(folder: Path) -> dict[str, Any]:
    """Every file of a staged sample with its SHA-256, size and, for an EXR, the format of its channel set."""
    from scopetwin.sim.datasets.validate import exr_format

    files = {}
    for f in sorted(folder.iterdir()):
        if f.name != SAMPLE_FILE and f.is_file():
            files[f.name] = {"sha256": sha256_file(f), "bytes": f.stat().st_size}
            if f.suffix == ".exr":
                files[f.name]["format"] = exr_format(f)
    return files


def generate_sample(plan_json: dict[str, Any], index: int, root: str, threads: int | None = None) -> dict[str, Any]:
    """Render sample ``index`` into ``root/samples/NNNNNN`` atomically; return its manifest record.

    Runs on a worker (any worker: the result depends only on the plan and ``index``). A sample
    folder that already exists is not redone (``status: "exists"``).
    """
    from scopetwin.scenes.io import write_json_atomic

    init_worker(threads)
    t0 = time.perf_counter()
    samples = Path(root) / SAMPLES
    final = samples / sample_name(index)
    record = {"index": index, "name": sample_name(index)}
    if not (final / SAMPLE_FILE).is_file():
        plan = Plan.from_json(plan_json, CONFIG_FILE)
        with StagedOutput(final, prefix=f"{TMP_PREFIX}{sample_name(index)}-", lock=True) as stage:
            out = plan.write_sample(index, stage)
            truth = out["truth"]
            truth.update(
                format=plan.format,
                sample=index,
                master_seed=plan.config.dataset.master_seed,
                kind=plan.config.dataset.kind,
                parameters=plan.parameters(index),
                versions=versions(SAMPLE_PACKAGES),
            )
            write_json_atomic(stage.path("truth.json"), truth)
            body = {
                "format": plan.format,
                **record,
                "kind": plan.config.dataset.kind,
                "files": _sample_record(stage.stage),
            }
            write_json_atomic(stage.path(SAMPLE_FILE), body)
            # False: another run finished the same sample first (identical bytes): keep theirs
            status = "written" if stage.rename() else "exists"
    else:
        status = "exists"
    body = read_sample_json(final)
    return {**body, "status": status, "seconds": time.perf_counter() - t0, **worker_identity()}


def worker_identity() -> dict[str, Any]:
    """Who is running this: ``{"worker", "host", "pid"}`` of this process (a Dask worker's address, or "local")."""
    worker = "local"
    try:
        from distributed import get_worker

        worker = str(get_worker().address)
    except (ImportError, ValueError):  # not inside a Dask worker
        pass
    return {"worker": worker, "host": socket.gethostname(), "pid": os.getpid()}


# -- the dataset folder: manifest, recovery, generation, verification -------------------------------
def read_sample_json(folder: Path) -> dict[str, Any]:
    """A sample folder's ``sample.json`` read safely (:func:`scopetwin.scenes.safe_read.read_json_inside`) and of a
    format this scopetwin reads.

    Raises
    ------
    InputError
        Not a regular file inside ``folder``, too large, nested too deep, not a JSON object, or a newer format.
    """
    body = read_json_inside(folder, SAMPLE_FILE, SAMPLE_FILE)
    check_format(body.get("format", 1), READABLE_FORMATS, f"{folder / SAMPLE_FILE}")
    return body


def _read_manifest(root: Path) -> tuple[list[dict[str, Any]], int]:
    """Parsed manifest lines and the number of unreadable ones (a line cut by a kill, a line nested too deep).

    A manifest that cannot be read safely (a link out of the folder, a FIFO, a device, over
    :data:`MANIFEST_LIMIT`) counts as one unreadable line and is logged: recovery rewrites it from the samples.
    """
    path = root / MANIFEST
    if not (path.exists() or path.is_symlink()):
        return [], 0
    try:
        real = resolve_inside(root, MANIFEST, MANIFEST)
        check_regular(real, MANIFEST, MANIFEST_LIMIT)
        text = read_text_input(real, MANIFEST, MANIFEST_LIMIT)
    except InputError as exc:
        log.warning("%s is not read: %s", path, exc)
        return [], 1
    rows, bad = [], 0
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            row = parse_json(line, MANIFEST, "line")
            int(row["index"])
            rows.append(row)
        except (InputError, KeyError, TypeError, ValueError):
            bad += 1
    return rows, bad


def _files_problem(files: Any) -> str | None:
    """Why ``sample.json``'s ``files`` is not a table of file names with their sizes and hashes, or None."""
    if not isinstance(files, dict):
        return f"{SAMPLE_FILE}: files is not a table"
    for name, meta in files.items():
        ok = isinstance(meta, dict) and isinstance(meta.get("sha256"), str)
        size = meta.get("bytes") if isinstance(meta, dict) else None
        if not ok or isinstance(size, bool) or not isinstance(size, int):
            return f"{SAMPLE_FILE}: files.{name} lacks its size (bytes) or hash (sha256)"
    return None


def _check_sample(folder: Path, expected: dict[str, Any] | None = None) -> str | None:
    """None if the folder's files match its sample.json (and ``expected`` hashes); else the reason.

    Nothing is opened that is not a regular file inside ``folder``: a sample folder that is a link, a file name that
    leaves the folder, a link out of it, a FIFO or a device is the reason.
    """
    if folder.is_symlink():
        return f"the sample folder is a symbolic link to {os.path.realpath(folder)}"
    try:
        body = read_sample_json(folder)
    except ScopetwinError as exc:
        return f"{SAMPLE_FILE} unreadable: {exc}"
    files = body.get("files", {})
    reason = _files_problem(files)
    if reason is not None:
        return reason
    if expected is not None and expected != files:
        return "hashes differ from the manifest"
    present = {f.name for f in folder.iterdir() if f.name != SAMPLE_FILE}
    if present != set(files):
        return f"files differ from {SAMPLE_FILE}: {sorted(present ^ set(files))}"
    for name, meta in files.items():
        try:
            p = resolve_inside(folder, name, name)
            size = check_regular(p, name, SAMPLE_FILE_LIMIT)
        except ScopetwinError as exc:
            return str(exc)
        if size != meta["bytes"] or sha256_file(p) != meta["sha256"]:
            return f"{name} does not match its hash"
    return None


def _manifest_line(rec: dict[str, Any]) -> dict[str, Any]:
    """A manifest line from a sample's record: its files, and the worker (host, pid) that made it.

    A sample re-listed from disk (``status: "recovered"``) has no known maker: ``worker`` is "recovered",
    ``host``/``pid`` are null and ``recovered_by`` names the process that listed it.
    """
    keep: dict[str, Any] = {k: rec[k] for k in ("index", "name", "kind", "files") if k in rec}
    line = {
        **keep,
        "status": rec.get("status", "written"),
        "seconds": round(float(rec.get("seconds", 0.0)), 3),
        "worker": rec.get("worker"),
        "host": rec.get("host"),
        "pid": rec.get("pid"),
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if line["status"] == "recovered":
        line.update(worker="recovered", host=None, pid=None, recovered_by=f"{socket.gethostname()}:{os.getpid()}")
    return line


def _append(fh: IO[str], row: dict[str, Any]) -> None:
    fh.write(json.dumps(row, separators=(",", ":")) + "\n")
    fh.flush()
    os.fsync(fh.fileno())


def remove_stale_temporaries(root: Path) -> tuple[list[str], list[str]]:
    """Remove the temporary sample folders of dead processes; keep those a live writer holds locked.

    Returns (removed names, kept names). A sample folder is staged with an ``flock`` held by the process writing
    it (:class:`~scopetwin.sim.measurement.StagedOutput` ``lock=True``), so a worker of an earlier run that is still
    finishing a sample (an external cluster outlives its client) keeps its folder.
    """
    removed: list[str] = []
    kept: list[str] = []
    samples = root / SAMPLES
    if not samples.is_dir():
        return removed, kept
    for p in sorted(samples.iterdir()):
        if p.name.startswith("."):
            (removed if remove_stale_stage(p) else kept).append(p.name)
    return removed, kept


def recover(root: Path) -> dict[str, Any]:
    """Tidy a dataset folder after an interruption; return what was found and done.

    Removes temporary sample folders of dead processes, drops unreadable/duplicate manifest lines and lines of
    samples that are gone or corrupt, deletes corrupt sample folders (they are redone), and lists finished
    samples the manifest does not know (the client died between rename and manifest). Call it holding the
    folder's :class:`~scopetwin.sim.datasets.lock.DatasetLock`.

    Returns
    -------
    dict
        ``listed`` (samples the manifest listed correctly), ``relisted`` (finished samples re-listed from disk),
        ``removed_temporary`` / ``kept_temporary`` (temporary folders removed / kept because a live process
        writes them), ``corrupt_removed``, ``dropped_manifest_lines`` and ``done`` (every finished sample).
    """
    from scopetwin.scenes.io import write_text_atomic

    samples = root / SAMPLES
    samples.mkdir(parents=True, exist_ok=True)
    removed_tmp, kept_tmp = remove_stale_temporaries(root)
    rows, bad_lines = _read_manifest(root)
    listed: dict[int, dict[str, Any]] = {}
    for line in rows:
        listed.setdefault(int(line["index"]), line)
    kept: list[dict[str, Any]] = []
    corrupt: list[int] = []
    relisted: list[int] = []
    folders = {int(p.name): p for p in samples.iterdir() if p.is_dir() and p.name.isdigit()}
    for idx, folder in sorted(folders.items()):
        reason = _check_sample(folder)
        if reason is not None:
            log.warning("sample %d is corrupt and is redone: %s", idx, reason)
            if folder.is_symlink():
                folder.unlink()  # the link, never what it points to
            else:
                shutil.rmtree(folder, ignore_errors=True)
            corrupt.append(idx)
            continue
        row = listed.get(idx)
        body = read_sample_json(folder)
        if row is None or row.get("files") != body["files"]:
            row = _manifest_line({**body, "status": "recovered"})
            relisted.append(idx)
        kept.append(row)
    dropped = bad_lines + len(rows) - len(kept) + len(relisted)
    if dropped or relisted or not (root / MANIFEST).exists():
        write_text_atomic(root / MANIFEST, "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in kept))
    return {
        "listed": len(kept) - len(relisted),
        "relisted": relisted,
        "removed_temporary": removed_tmp,
        "kept_temporary": kept_tmp,
        "corrupt_removed": corrupt,
        "dropped_manifest_lines": dropped,
        "done": sorted(folders.keys() - set(corrupt)),
    }


def _list_from_disk(root: Path, listed: set[int], fh: IO[str]) -> list[int]:
    """Append manifest lines for finished sample folders this run has not listed (a result lost to an interruption).

    Only folders not in ``listed`` are checked (their hashes against their ``sample.json``); returns their indices.
    """
    found = []
    samples = root / SAMPLES
    for p in sorted(samples.iterdir()) if samples.is_dir() else []:
        if not (p.is_dir() and p.name.isdigit()) or int(p.name) in listed:
            continue
        if _check_sample(p) is None:
            body = read_sample_json(p)
            _append(fh, _manifest_line({**body, "status": "recovered"}))
            listed.add(int(p.name))
            found.append(int(p.name))
    return found


def _write_plan(root: Path, plan: Plan) -> None:
    from scopetwin.scenes.io import write_json_atomic

    path = root / CONFIG_FILE
    new = plan.to_json()
    if path.exists() or path.is_symlink():
        old = read_config(root)
        if old.get("format") != new["format"]:
            Plan.from_json(old, str(path)).check_writable(str(root))
        if old != json.loads(json.dumps(new)):
            raise DatasetError(
                f"{root} already holds a different dataset ({CONFIG_FILE} differs); choose another "
                "--out or `scopetwin dataset resume` it"
            )
        return
    write_json_atomic(path, new)


def parse_indices(text: str | None, count: int) -> list[int]:
    """``"A:B"`` -> [A, B) within [0, count); None -> all."""
    if text is None:
        return list(range(count))
    try:
        a, b = (int(t) if t else d for t, d in zip(text.split(":"), (0, count), strict=True))
    except ValueError:
        raise DatasetError(f"--indices must look like A:B (half-open), got {text!r}") from None
    if not 0 <= a < b <= count:
        raise DatasetError(f"--indices {text} must satisfy 0 <= A < B <= count ({count})")
    return list(range(a, b))


def _make_folder(root: Path) -> bool:
    """Create the dataset folder; True when this call created it (so a refused start can remove it again).

    A folder that is a symbolic link is refused: the samples are not written through it."""
    _refuse_link(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    try:
        root.mkdir()
    except FileExistsError:
        if not root.is_dir():
            raise DatasetError(f"--out {root} is a file, not a folder") from None
        return False
    return True


def _has_samples(root: Path) -> bool:
    samples = root / SAMPLES
    return samples.is_dir() and any(p.name.isdigit() for p in samples.iterdir())


def _finish_folder(root: Path, listed: set[int], fh: IO[str], state: dict[str, Any]) -> None:
    """After the workers are done or gone: list finished samples no result reported, remove dead temporaries."""
    from scopetwin.sim.signals import deferred_signals

    with deferred_signals():
        state["relisted_at_end"] = _list_from_disk(root, listed, fh)
        removed, kept = remove_stale_temporaries(root)
        state["removed_temporary_at_end"], state["kept_temporary_at_end"] = removed, kept


def task_keys(plan_json: dict[str, Any], root: Path, indices: Sequence[int]) -> list[str]:
    """The Dask keys of samples ``indices``: one per sample of this plan *and* this folder.

    A scheduler runs one task per key and hands its result to every client that asks for the key; so a second run of
    the same plan into another folder on a shared scheduler must get keys of its own, or it would be handed the first
    run's samples, written into the first run's folder.
    """
    tag = hashlib.sha256(json.dumps([plan_json, str(root.resolve())], sort_keys=True).encode()).hexdigest()[:12]
    return [f"scopetwin-sample-{tag}-{i:06d}" for i in indices]


def generate(
    plan: Plan,
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    threads: int | None = None,
    indices: Sequence[int] | None = None,
    progress: bool = True,
    client: Any | None = None,
) -> dict[str, Any]:
    """Generate (or finish) the samples ``indices`` of a dataset in ``out``.

    The run holds the folder's :class:`~scopetwin.sim.datasets.lock.DatasetLock` throughout (a second run on the same
    folder is refused at once), tidies it (:func:`recover`), then renders what is missing. However it ends
    (success, failed samples, Ctrl-C, SIGTERM/SIGHUP as :class:`~scopetwin.sim.signals.Terminated`), every finished
    sample
    on disk is listed in the manifest when it returns or raises, with the host and pid of the worker process
    that made it, and the temporary folders of dead processes are gone. A folder this call created is removed
    again when the run stops before any sample was written (a scheduler that does not answer, an interruption
    while the cluster starts), so a refused start leaves nothing behind.

    Parameters
    ----------
    plan : Plan
        Validated config (:meth:`Plan.build` checks every sample's setup before this is called).
    out : path
        Dataset folder (created; a folder holding another dataset is refused).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``), used unchanged.
    workers : int, optional
        Local worker processes (default one per core); 0 works in this process without Dask.
    threads : int, optional
        Dr.Jit threads per worker (default: 1 on the local cluster, the library default elsewhere).
    indices : sequence of int, optional
        Which samples (default all ``count``).
    progress : bool
        Show a progress bar (rate, ETA, and ``failed=N`` once a sample failed; failed samples do not advance it).
    client : distributed.Client, optional
        Use this client (and its cluster) instead of opening one.

    Raises
    ------
    DatasetBusy
        Another live run holds the folder (the message names its host and pid).
    DatasetError
        A different dataset is in the folder, the scheduler does not answer, or samples failed (the others are
        written and listed).
    """
    from tqdm import tqdm

    root = Path(out)
    if scheduler and client is None:
        check_scheduler(scheduler)
    created = _make_folder(root)
    try:
        with DatasetLock(root):
            return _generate_locked(plan, root, scheduler, workers, threads, indices, progress, client, tqdm)
    except DatasetBusy:
        raise  # the folder is the other run's
    except BaseException:
        if created and not _has_samples(root):
            shutil.rmtree(root, ignore_errors=True)
        raise


def _generate_locked(
    plan: Plan,
    root: Path,
    scheduler: str | None,
    workers: int | None,
    threads: int | None,
    indices: Sequence[int] | None,
    progress: bool,
    client: Any | None,
    tqdm: Any,
) -> dict[str, Any]:
    _write_plan(root, plan)
    plan.check_writable(str(root))
    state = recover(root)
    wanted = list(range(plan.config.dataset.count)) if indices is None else list(indices)
    listed = set(state["done"])
    todo = [i for i in wanted if i not in listed]
    state["requeued"] = len(todo)
    if threads is None and scheduler is None and workers != 0:
        threads = 1
    plan_json = plan.to_json()
    t0 = time.perf_counter()
    failures: dict[int, str] = {}
    written = 0
    with contextlib.ExitStack() as stack:  # unwinds in reverse: tasks, bar, client, then the folder's clean-up
        # never through a link planted at the manifest's path (scenes.io.open_append refuses one)
        fh = stack.enter_context(open_append(root / MANIFEST))

        def record(rec: dict[str, Any]) -> None:
            _append(fh, _manifest_line(rec))
            listed.add(int(rec["index"]))

        stack.callback(_finish_folder, root, listed, fh, state)  # after the workers are closed
        if client is None and (workers != 0 or scheduler):
            client = stack.enter_context(dask_client(scheduler, workers))
        bar = stack.enter_context(
            tqdm(
                total=len(wanted),
                initial=len(wanted) - len(todo),
                unit="sample",
                desc="dataset",
                disable=not progress,
                smoothing=0.1,
            )
        )
        args = [(plan_json, i, str(root.resolve()), threads) for i in todo]
        keys = task_keys(plan_json, root, todo)
        tasks = run_tasks(generate_sample, args, client, keys, on_abandon=lambda k, rec: record(rec))
        stack.callback(tasks.close)  # first on the way out: give up what is queued, list what has finished
        for k, rec, err in tasks:
            if err is not None:
                failures[todo[k]] = failure_text(err)
                bar.set_postfix(failed=len(failures))
                continue
            record(rec)
            written += rec["status"] == "written"
            bar.update(1)
    seconds = time.perf_counter() - t0
    result = {
        "out": str(root),
        "requested": len(wanted),
        "already_done": len(wanted) - len(todo),
        "written": written,
        "failed": failures,
        "seconds": seconds,
        "samples_per_minute": 60.0 * len(todo) / seconds if todo and seconds > 0 else None,
        "recovery": state,
    }
    if failures:
        first = next(iter(failures.items()))
        raise DatasetError(
            f"{len(failures)} of {len(todo)} sample(s) failed (first: sample {first[0]}: {first[1]}); the others "
            f"are written and listed; fix the cause and run `scopetwin dataset resume {root}`"
        )
    return result


def read_config(root: str | Path) -> dict[str, Any]:
    """A dataset folder's ``dataset.json``, read safely (a regular file inside the folder, bounded size and depth).

    Raises
    ------
    DatasetError
        The folder has no ``dataset.json``.
    InputError
        It is a link out of the folder, a FIFO or a device, too large, nested too deep, or not a JSON object.
    """
    path = Path(root) / CONFIG_FILE
    if not (path.exists() or path.is_symlink()):
        raise DatasetError(f"{root} is not a dataset folder (no {CONFIG_FILE})")
    return read_json_inside(root, CONFIG_FILE, CONFIG_FILE)


def load_plan(root: str | Path) -> Plan:
    """The plan stored in a dataset folder (:func:`read_config`; a format this scopetwin reads)."""
    data = read_config(root)
    try:
        return Plan.from_json(data, str(Path(root) / CONFIG_FILE))
    except (KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(f"{Path(root) / CONFIG_FILE} lacks what a dataset plan holds ({exc!r})") from None


def verify(root: str | Path) -> dict[str, Any]:
    """Check every sample against the manifest and its hashes (docs/contract.md, ``dataset verify``).

    Returns ``{"complete": n, "missing": [...], "corrupt": [...], "duplicates": [...]}`` plus ``count``,
    ``unlisted`` (finished folders the manifest lacks), ``temporary`` (left-over temporary folders),
    ``bad_manifest_lines``, ``invalid`` (samples whose hashes match but whose files break their format's JSON
    Schemas or hold values that cannot be true: non-finite numbers, values out of range, an image without signal,
    inconsistent maps; :func:`scopetwin.sim.datasets.validate.check_sample`), ``format`` and ``ok``. An invalid
    sample does not count as complete.
    """
    from scopetwin.sim.datasets.validate import check_sample, schema_errors

    root = Path(root)
    plan = load_plan(root)
    config_errors = schema_errors(read_config(root), "dataset") if plan.format >= 2 else []
    count = plan.config.dataset.count
    rows, bad = _read_manifest(root)
    by_index: dict[int, list[dict[str, Any]]] = {}
    for row in rows:
        by_index.setdefault(int(row["index"]), []).append(row)
    samples = root / SAMPLES
    if samples.is_symlink():
        config_errors.append(f"{SAMPLES} is a symbolic link to {os.path.realpath(samples)}; nothing in it is read")
    entries = list(samples.iterdir()) if samples.is_dir() and not samples.is_symlink() else []
    temporary = sorted(p.name for p in entries if p.name.startswith("."))
    folders = {p.name: p for p in entries if p.is_dir() and not p.name.startswith(".")}
    duplicates = sorted(i for i, r in by_index.items() if len(r) > 1)
    stray = sorted(n for n in folders if not (n.isdigit() and len(n) == 6 and int(n) < count))
    missing, corrupt, unlisted, complete = [], [], [], 0
    invalid: list[dict[str, Any]] = []
    for i in range(count):
        folder = folders.get(sample_name(i))
        if folder is None:
            missing.append(i)
            continue
        listed = by_index.get(i)
        reason = _check_sample(folder, listed[0]["files"] if listed else None)
        problems = check_sample(folder, plan.format, READABLE_FORMATS) if reason is None else []
        if reason is not None:
            corrupt.append({"index": i, "reason": reason})
        elif problems:
            invalid.append({"index": i, "reasons": problems})
        elif not listed:
            unlisted.append(i)
        elif i not in duplicates:
            complete += 1
    extra = sorted(i for i in by_index if not 0 <= i < count)
    result: dict[str, Any] = {
        "complete": complete,
        "missing": missing,
        "corrupt": corrupt,
        "duplicates": duplicates,
        "count": count,
        "unlisted": unlisted,
        "temporary": temporary,
        "stray_folders": stray,
        "manifest_out_of_range": extra,
        "bad_manifest_lines": bad,
        "invalid": invalid,
        "format": plan.format,
        "config_errors": config_errors,
    }
    result["in_use_by"] = holder(root)  # a live run is still writing (its lock file's contents)
    result["ok"] = complete == count and not (
        missing or corrupt or duplicates or unlisted or temporary or stray or extra or bad or invalid or config_errors
    )
    return result
