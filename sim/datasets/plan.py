"""The plan of a dataset: a validated config with its resolved base setup, what every worker gets.

:meth:`Plan.build` resolves the base setup of the sample kind and (by default) builds every requested sample's
setup, so a config that would fail on sample 917 fails before any work.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from scopetwin.scenes.limits import check_render
from scopetwin.scenes.setup import Setup
from scopetwin.sim.datasets import cmu, grin, part1
from scopetwin.sim.datasets.config import DatasetConfig, DatasetError, check_parameters, config_from_dict
from scopetwin.sim.datasets.seeding import draw_parameters
from scopetwin.sim.measurement import StagedOutput

#: The format of the dataset folder this scopetwin writes (``dataset.json`` ``"format"``; docs/contract.md,
#: "Datasets"). 2: samples carry ``maps.exr``, ``camera_opencv`` and format numbers in their JSON files.
FORMAT_VERSION = 2
#: Formats this scopetwin reads (``verify``, :func:`scopetwin.open_dataset`); it writes only :data:`FORMAT_VERSION`.
READABLE_FORMATS = (1, 2)


def _capability(kind: str) -> None:
    """Raise when the renderer of a sample kind is not part of this installation."""
    if kind == "cmu":
        import importlib.util

        if importlib.util.find_spec("scopetwin.scenes.mitsuba.cmu") is None:
            raise DatasetError(
                "sample kind 'cmu' needs the four-channel microscope renderer "
                "(scenes.mitsuba.cmu), which this installation does not have"
            )


@dataclass(frozen=True)
class Plan:
    """A validated config with its resolved base setup: what is sent to every worker."""

    config: DatasetConfig
    base: dict[str, Any]
    format: int = FORMAT_VERSION

    @classmethod
    def build(cls, cfg: DatasetConfig, indices: Iterable[int] | None = None, check: bool = True) -> Plan:
        """Resolve the base setup and (``check``) build every requested sample's setup to validate it."""
        _capability(cfg.dataset.kind)
        if cfg.dataset.kind == "grin":
            base = grin.grin_base(cfg)
        elif cfg.dataset.kind == "cmu":
            base = cmu.cmu_base(cfg)
        else:
            base = part1.base_setup_dict(cfg)
            scene = base.get("scene")
            want = {"deflectometry": ("deflectometry",), "calibration": ("target", "mirror")}[cfg.dataset.kind]
            if scene not in want:
                raise DatasetError(
                    f"dataset config: key dataset.setup: {cfg.dataset.setup!r} is a {scene!r} scene; "
                    f"{cfg.dataset.kind!r} samples need {' or '.join(want)}"
                )
        plan = cls(cfg, base)
        if check:
            for i in range(cfg.dataset.count) if indices is None else indices:
                sample = plan.setup_of(i)
                if isinstance(sample, Setup):  # Part I: the render's memory and time, before any folder exists
                    nx, ny = sample.camera.pixels
                    check_render(nx, ny, sample.render.spp, f"dataset sample {i} ({nx} x {ny} px)")
        return plan

    def to_json(self) -> dict[str, Any]:
        """The plan as stored in ``dataset.json`` and sent to the workers."""
        return {
            "format": self.format,
            "config": self.config.model_dump(mode="json", exclude_none=True),
            "base_setup": self.base,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any], label: str = "dataset.json") -> Plan:
        """A plan from :meth:`to_json` (``label`` names the source in error messages)."""
        fmt = data.get("format")
        if fmt not in READABLE_FORMATS:
            raise DatasetError(
                f"{label}: dataset format {fmt!r} is not one this scopetwin reads (formats "
                f"{', '.join(map(str, READABLE_FORMATS))})"
                + ("; install a newer scopetwin to read it" if isinstance(fmt, int) and fmt > FORMAT_VERSION else "")
            )
        return cls(config_from_dict(data["config"], label), data["base_setup"], int(fmt))

    def check_writable(self, label: str) -> None:
        """Raise unless this scopetwin writes samples of the plan's format (a folder of an older format is read,
        verified and exported, not extended: its samples would differ from the new ones)."""
        if self.format != FORMAT_VERSION:
            raise DatasetError(
                f"{label} is a dataset of format {self.format}; this scopetwin writes format {FORMAT_VERSION} "
                "samples and does not mix them into it: generate a new dataset from the same config (reading, "
                "verifying and exporting the old one still work)"
            )

    def parameters(self, index: int) -> dict[str, Any]:
        """The varied quantities of sample ``index`` (:func:`~scopetwin.sim.datasets.seeding.draw_parameters`)."""
        groups: dict[str, Sequence[str]] | None = None
        if self.config.dataset.kind == "cmu":
            groups = {"splitter": list(self.base["splitters"]), "channel": cmu.cmu_channels(self.config, self.base)}
        params = draw_parameters(self.config, index, groups)
        check_parameters(params, index)  # drawn values are checked like fixed ones, before any work with them
        return params

    def setup_of(self, index: int) -> Any:
        """What sample ``index`` renders: a Part I :class:`~scopetwin.scenes.setup.Setup`, a GRIN (setup, target) pair
        or a
        :class:`~scopetwin.sim.datasets.cmu.CmuSample`, validated."""
        params = self.parameters(index)
        if self.config.dataset.kind == "grin":
            return grin.grin_sample(self.base, index, params)
        if self.config.dataset.kind == "cmu":
            return cmu.cmu_sample(self.config, self.base, index, params)
        return part1.part1_setup(self.config, self.base, index, params)

    def write_sample(self, index: int, stage: StagedOutput) -> dict[str, Any]:
        """Render sample ``index`` and write its files into ``stage``; returns ``{"files", "truth"}``."""
        writers: dict[str, Callable[[DatasetConfig, int, Any, StagedOutput], dict[str, Any]]] = {
            "grin": grin.write_grin,
            "cmu": cmu.write_cmu,
        }
        writer = writers.get(self.config.dataset.kind, part1.write_part1)
        return writer(self.config, index, self.setup_of(index), stage)

    def sample_bytes(self, index: int = 0) -> int:
        """An upper estimate of the bytes sample ``index`` takes on disk (checked against the free space first).

        Images count as uncompressed float32 (4 bytes a pixel; the noise of a real image leaves little to
        compress; a fringe setup writes one per frame of its sequence and no preview), a preview PNG as one byte a
        pixel, a height map as 4 bytes a node per channel (a deflectometry sample also stores three normal
        components), the per-pixel maps as 4 bytes a pixel per channel, plus
        256 KiB for the truth JSON and the sample record.
        """
        kind = self.config.dataset.kind
        preview = 1 if self.config.dataset.preview else 0
        sample = self.setup_of(index)
        extra = 256 << 10
        if kind == "grin":
            setup = sample[0]
            w = self.config.grin.width or setup.camera.width_px
            h = self.config.grin.height or setup.camera.height_px
            return int(w * h * 4 + extra)
        if kind == "cmu":
            _, _, h, w = cmu.image_box(self.config, sample.setup)
            px = h * w * len(sample.channels)
            maps = 2 * 4 * len(sample.channels) if self.config.dataset.maps else 0  # object_xy per channel
            return int(px * 4 + px * preview + h * w * maps + (4 << 20) + extra)  # + the splitters' height maps
        cam = sample.camera_model
        px = cam.nx * cam.ny
        nodes = 0 if sample.substrate is None else sample.substrate.surface.grid[0] * sample.substrate.surface.grid[1]
        maps = 4 * 17 if self.config.dataset.maps else 0  # the channels of maps.exr, float32 (before compression)
        if sample.fringe_sequence is not None:  # a fringe setup: one image per frame, no preview
            return int(px * (4 * len(sample.fringe_sequence) + maps) + nodes * 4 * 5 + extra)
        return int(px * (4 + preview + maps) + nodes * 4 * 5 + extra)
