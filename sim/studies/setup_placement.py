"""The ``setup`` study: which setup brings data close enough to the frame regions?

The start height of thesis §1.4 rests on the surface's maxima over the frame regions (|y| >= 24 mm on the §1.10
substrate), where there are no data; with the thesis's pattern the last whole markers reach |y| ~ 22.3-23.4 mm and
the maxima lie up to 4.5 mm further out, at the substrate's ends. This study varies what a setup can change —
the marker pitch (finer markers are imaged whole closer to the ROI edge) and the depth of the holding frame's
support (how far the substrate overhangs the ROI, so how far the fit must extrapolate) — and reports, over
surfaces of the thesis's kind with nm-level broadband content, the worst absolute error and its uncertainty.
Inputs are exact marker-centre images (:func:`scopetwin.sim.truth.marker_truth`) plus centroid noise, as in the
``coverage`` study.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed
from scopetwin.sim.studies.coverage import coverage_task
from scopetwin.sim.studies.tables import Table, jsonable

#: Setup variants: (label, overrides of the §1.10 preset).
VARIANTS: list[tuple[str, dict[str, Any]]] = [
    ("seed: pitch 1.5 mm, support 4.5 mm", {}),
    ("pitch 1.0 mm", {"pattern": {"markers": [49, 49], "pitch": [1.0, 1.0], "radius": 1 / 3, "ref_radius": 0.47}}),
    ("pitch 0.75 mm", {"pattern": {"markers": [65, 65], "pitch": [0.75, 0.75], "radius": 0.25, "ref_radius": 0.35}}),
    ("support 3.0 mm", {"substrate": {"size": [25.2, 54.0]}}),
    ("support 1.5 mm", {"substrate": {"size": [25.2, 51.0]}}),
    (
        "pitch 0.75 mm, support 1.5 mm",
        {
            "pattern": {"markers": [65, 65], "pitch": [0.75, 0.75], "radius": 0.25, "ref_radius": 0.35},
            "substrate": {"size": [25.2, 51.0]},
        },
    ),
]
FAMILIES = ("gauss+broadband", "abc+broadband")


def setup_placement(ctx: StudyContext, per_family: int = 4, noise_px: float = 0.005) -> StudyResult:
    """Worst and median absolute error per setup variant over ``per_family`` surfaces of each family."""
    args = [
        (fam, 2000 + 41 * k + i, noise_px, over)
        for over in (v[1] for v in VARIANTS)
        for i, fam in enumerate(FAMILIES)
        for k in range(per_family)
    ]
    rows = ctx.map(coverage_task, args, "setup: reconstruct")
    labels = [label for label, _ in VARIANTS for _ in FAMILIES for _ in range(per_family)]
    notes = [f"{lab}: surface failed: {error_text(r)}" for lab, r in zip(labels, rows, strict=True) if failed(r)]
    cells = []
    data = []
    for label, _ in VARIANTS:
        rs = [r for lab, r in zip(labels, rows, strict=True) if lab == label and not failed(r) and "error" not in r]
        bad = [r for lab, r in zip(labels, rows, strict=True) if lab == label and not failed(r) and "error" in r]
        notes += [f"{label}: {r['family']} seed {r['seed']}: {r['error']}" for r in bad]
        data.append({"setup": label, "rows": rs})
        if not rs:
            cells.append([label, 0] + [None] * 7)
            continue
        a = np.abs([r["roi_absolute_um"] for r in rs])
        a0 = np.abs([r["uncorrected_absolute_um"] for r in rs])
        u = np.array([r["u_abs_um"] for r in rs])
        sh = np.array([r["roi_shape_um"] for r in rs])
        cells.append(
            [
                label,
                len(rs),
                int(np.median([r["markers"] for r in rs])),
                float(np.median(a0)),
                float(a0.max()),
                float(np.median(a)),
                float(a.max()),
                float(np.max(u)),
                float(np.median(sh)),
                "yes" if a.max() <= 0.05 else "no",
            ]
        )
    table = Table(
        "Absolute height against the setup (surfaces with broadband content)",
        columns=[
            "setup",
            "surfaces",
            "markers",
            "|abs| median, fit (µm)",
            "|abs| max, fit (µm)",
            "|abs| median (µm)",
            "|abs| max (µm)",
            "u_abs max (µm)",
            "shape median (µm)",
            "|abs| <= 0.05 µm on every surface",
        ],
        cells=cells,
        note=f"{per_family} surfaces per family ({', '.join(FAMILIES)}; 8-20 mm, 20-60 µm, 1-5 nm broadband); exact "
        f"marker images + {noise_px} px centroid noise, ideal setup. 'support': depth of the holding frame's support "
        "beyond the 48 mm ROI (substrate length 48 + 2 x support). 'fit': before the posterior start-height "
        "correction.",
    )
    return StudyResult(
        "Study: which setup brings data close enough to the frame regions",
        "Marker pitch and the holding frame's support depth against the absolute-height error (thesis §1.4).",
        [table],
        [],
        {"setups": jsonable(data)},
        notes,
    )
