"""Datasets of a fringe setup (phase-measuring deflectometry in the §1.10 geometry): every frame of the sequence and
its JSON per sample with the truth, read back by the reader, checked by ``verify``.

Acceptance: a sample holds one EXR per frame of the setup's sequence and ``fringes.json``; the reader gives the
K frames in the sequence's order; decoding them (:func:`scopetwin.recon.fringes.phase.decode_display`) gives the
per-pixel truth ``pattern_xy`` of ``maps.exr`` within 3 of the decoder's reported standard deviation on >= 95 % of
the decoded ROI pixels; ``verify`` passes the sample and names a ``fringes.json`` whose frames are not the sample's.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.recon.fringes.phase import decode_display
from scopetwin.sim.datasets.config import config_from_dict
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.reader import DatasetReadError, open_dataset
from scopetwin.sim.datasets.store import MANIFEST, SAMPLE_FILE, SAMPLES, generate, sha256_file, verify

pytestmark = pytest.mark.mitsuba

#: The fringe preset seen by a 4 x 4 binned camera (same field of view), periods 64 and 8 mm: 16 frames.
CONFIG = {
    "dataset": {
        "kind": "deflectometry",
        "setup": "thesis-1.10-fringes",
        "count": 1,
        "master_seed": 12,
        "spp": 4,
        "noise": True,
        "preview": False,
    },
    "setup": {
        "camera": {"pixels": [340, 256], "pixel_pitch": 0.0186},
        "fringes": {"sequence": {"periods": [64.0, 8.0], "steps": 4}},
    },
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("fringe-dataset") / "ds"
    generate(Plan.build(config_from_dict(CONFIG, "fringe dataset")), root, workers=0, progress=False)
    return root


def test_a_fringe_sample_holds_every_frame_and_decodes_to_its_truth(dataset):
    ds = open_dataset(dataset)
    (sample,) = list(ds)
    files = set(sample.meta["files"])
    frames = sorted(n for n in files if n.startswith("fringe_"))
    assert len(frames) == 16 and {"fringes.json", "maps.exr", "surface.exr", "truth.json"} <= files
    assert "image.exr" not in files and sample.truth["frames"] == frames and sample.truth["markers"] == []
    m = sample.fringes
    assert m.images.shape == (16, 256, 340) and m.noise and m.exposure_s == sample.truth["exposure_s"]
    assert np.array_equal(m.images[3], sample.images["fringe_0003"])
    seq = m.sequence
    stacks = {d: [m.images[[seq.index(d, p, k) for k in range(4)]] for p in range(2)] for d in "xy"}
    coords = decode_display(stacks["x"], stacks["y"], seq.periods_mm, tuple(m.display.size_mm))
    truth = sample.maps["pattern_xy"]
    ok = coords.valid & sample.maps["roi"] & np.all(np.isfinite(truth), axis=-1)
    assert ok.sum() > 0.5 * sample.maps["roi"].sum()  # most of the ROI's pixels are decoded
    z = np.abs(np.stack([coords.u - truth[..., 0], coords.v - truth[..., 1]]))[:, ok]
    z /= np.stack([coords.u_std, coords.v_std])[:, ok]
    assert np.mean(np.all(z <= 3.0, axis=0)) >= 0.95, np.percentile(z, [50, 95, 99])


def test_verify_passes_the_sample_and_names_frames_that_are_not_the_sample_s(dataset, tmp_path):
    import shutil

    assert verify(dataset)["ok"]
    bad = tmp_path / "bad"
    shutil.copytree(dataset, bad)
    folder = bad / SAMPLES / "000000"
    path = folder / "fringes.json"
    data = json.loads(path.read_text())
    data["frames"] = data["frames"][:-1]  # one frame fewer than the sample holds
    path.write_text(json.dumps(data))
    body = json.loads((folder / SAMPLE_FILE).read_text())  # hashes kept consistent: the content is what is wrong
    body["files"]["fringes.json"].update(sha256=sha256_file(path), bytes=path.stat().st_size)
    (folder / SAMPLE_FILE).write_text(json.dumps(body))
    rows = [json.loads(line) for line in (bad / MANIFEST).read_text().splitlines() if line.strip()]
    for row in rows:
        row["files"] = body["files"]
    (bad / MANIFEST).write_text("".join(json.dumps(row) + "\n" for row in rows))
    result = verify(bad)
    assert not result["ok"] and result["complete"] == 0
    (invalid,) = result["invalid"]
    assert any("fringes.json" in r and "frames" in r for r in invalid["reasons"]), invalid
    with pytest.raises(DatasetReadError, match="fringe"):
        _ = open_dataset(bad)[0].fringes
