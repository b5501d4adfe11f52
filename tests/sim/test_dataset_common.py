"""A tiny deflectometry dataset config shared by the dataset tests (small images, few markers); no tests here."""

from __future__ import annotations

from pathlib import Path

TINY = """
[dataset]
kind = "deflectometry"
setup = "thesis-1.10-deflectometry"
count = {count}
master_seed = 7
spp = 4
noise = true
preview = false

[setup.camera]
pixels = [170, 128]
pixel_pitch = 0.0372

[setup.pattern]
markers = [9, 9]
pitch = [5.0, 5.0]
radius = 1.5
ref_radius = 2.1

[setup.substrate.surface]
grid = [32, 64]

[vary]
surface_range_um = {{ uniform = [20.0, 60.0] }}
surface_correlation_length = {{ sweep = [8.0, 16.0] }}
camera_shift = {{ normal = [0.0, 0.2] }}
exposure_fill = {{ uniform = [0.4, 0.9] }}
"""


def write_tiny(folder: Path, count: int = 10, extra: str = "") -> Path:
    path = folder / "tiny.toml"
    path.write_text(TINY.format(count=count) + extra)
    return path
