"""GRIN samples (kind ``grin``, thesis Part III §8.5): the objective array's setup and target, and the writer."""

from __future__ import annotations

import json
from typing import Any

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim.datasets.config import SAMPLE_PACKAGES, DatasetConfig, DatasetError
from scopetwin.sim.datasets.seeding import sample_seed
from scopetwin.sim.measurement import StagedOutput, versions


def grin_base(cfg: DatasetConfig) -> dict[str, Any]:
    """The GRIN setup every sample starts from (preset/TOML plus ``[setup]``), as a JSON dictionary."""
    from scopetwin.scenes.grin.setup import load_grin_setup

    try:
        setup = load_grin_setup(cfg.dataset.setup, cfg.setup or None)
    except ScopetwinError as exc:
        raise DatasetError(f"dataset config: key dataset.setup / [setup]: {exc}") from None
    return json.loads(setup.to_json())


def grin_sample(base: dict[str, Any], index: int, params: dict[str, Any]) -> tuple[Any, Any]:
    """The GRIN setup and §8.5 target (name and offset varied) of sample ``index``; the target must fit the field."""
    from scopetwin.scenes.grin.setup import grin_setup_from_dict
    from scopetwin.scenes.grin.targets import target

    setup = grin_setup_from_dict(base, f"sample {index}")
    tgt = target(str(params.get("target", "grid-25")), tuple(params.get("target_offset", (0.0, 0.0))))
    try:
        tgt.check_field(setup.object.field_radius)
    except ScopetwinError as exc:
        raise DatasetError(f"sample {index}: key vary.target_offset: {exc}") from None
    return setup, tgt


def write_grin(cfg: DatasetConfig, index: int, sample: tuple[Any, Any], stage: StagedOutput) -> dict[str, Any]:
    """Render sample ``index`` (setup and target) at best focus (thesis §8.3) into ``stage``; returns files and
    truth."""
    from scopetwin.scenes.grin.analysis import analyse
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.grin import render_image
    from scopetwin.sim.datasets.validate import check_image

    setup, tgt = sample
    rep = analyse(setup, samples=16)
    stack = setup.stack(image_distance=rep.image_distance_mm)
    if rep.stop_radius_mm is not None:
        stack = stack.with_stop_radius(rep.stop_radius_mm)
    seed = sample_seed(cfg.dataset.master_seed, index, "render")
    g = cfg.grin
    whole = setup.array.nx * setup.array.ny > 1 and g.width is None and g.height is None
    axis0 = setup.array.axes()[0]
    centre = (0.0, 0.0) if whole else (float(axis0[0]), float(axis0[1]))  # a window: objective 0
    img = render_image(
        setup,
        stack,
        tgt,
        spp=cfg.dataset.spp,
        width=g.width,
        height=g.height,
        step_mm=g.step_mm,
        center=centre,
        seed=seed,
    )
    check_image(img, f"sample {index}: the render")
    prov = {"seed": seed, "spp": cfg.dataset.spp, "renderer": "mitsuba-grin", "versions": versions(SAMPLE_PACKAGES)}
    write_image(stage.path("image.exr"), img, setup.to_json(), prov, scopetwin_format="image/1")
    truth = {
        "setup": setup.name,
        "scene": "grin",
        "target": {"name": tgt.name, "offset": list(tgt.offset), "period": tgt.period, "feature": tgt.feature},
        "image_distance_mm": rep.image_distance_mm,
        "magnification": rep.magnification,
        "na_object": rep.na_object,
        "centre_mm": list(centre),
        "seeds": {"render": seed},
        "setup_json": json.loads(setup.to_json()),
    }
    files = {"image": "image.exr"}
    if cfg.dataset.maps:
        from scopetwin.sim.datasets.maps import MAPS_FILE, MAPS_FORMAT, MAPS_VERSION, grin_object_maps, write_maps

        maps = grin_object_maps(setup, stack, img.shape[1], img.shape[0], centre)
        write_maps(stage.path(MAPS_FILE), maps, cfg.dataset.maps_compression)
        files["maps"] = MAPS_FILE
        truth["maps"] = {"file": MAPS_FILE, "format": f"{MAPS_FORMAT}/{MAPS_VERSION}", "layers": list(maps)}
    return {"files": files, "truth": truth}
