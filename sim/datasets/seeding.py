"""Per-sample randomness and the varied quantities of each sample (:mod:`scopetwin.sim.datasets`, "Determinism").

Every random quantity of sample i comes from ``SeedSequence([master_seed, i, crc32(name)])``, so sample i is the
same bytes whatever worker renders it, in whatever order, alone or with others; ``sweep`` keys form a cartesian
grid that sample i walks through (i modulo the grid size).
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from scopetwin.sim.datasets.config import DOMAINS, DatasetConfig, DatasetError, Domain, Value


def _sequence(master_seed: int, index: int, name: str) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(master_seed), int(index), zlib.crc32(name.encode())])


def sample_rng(master_seed: int, index: int, name: str) -> np.random.Generator:
    """The generator of quantity ``name`` of sample ``index`` (independent of every other sample and name)."""
    return np.random.default_rng(_sequence(master_seed, index, name))


def sample_seed(master_seed: int, index: int, name: str) -> int:
    """A 31-bit seed for quantity ``name`` of sample ``index`` (surface, render, ...)."""
    return int(_sequence(master_seed, index, name).generate_state(1, dtype=np.uint32)[0] & 0x7FFFFFFF)


def sweep_cell(cfg: DatasetConfig, index: int) -> dict[str, Value]:
    """The values of the ``sweep`` keys for sample ``index``: cell ``index`` modulo the grid size (config order)."""
    sweeps = [(k, d.sweep) for k, d in cfg.vary.items() if d.sweep is not None]
    if not sweeps:
        return {}
    sizes = [len(v) for _, v in sweeps]
    cell = np.unravel_index(index % int(np.prod(sizes)), sizes)
    return {k: v[int(c)] for (k, v), c in zip(sweeps, cell, strict=True)}


def draw_parameters(cfg: DatasetConfig, index: int, groups: dict[str, Sequence[str]] | None = None) -> dict[str, Any]:
    """The varied quantities of sample ``index`` (JSON-ready; vectors as lists).

    A quantity with a ``per`` group (:class:`Domain`) becomes ``{member: value}`` over ``groups[per]``
    (channels default to the unit's four); each member has its own generator (``name:member``), so a
    member's value does not depend on which other members the setup has.
    """
    cell = sweep_cell(cfg, index)
    out: dict[str, Any] = {}
    for name, dist in cfg.vary.items():
        dom = DOMAINS[name]
        dims = dom.dims
        members = _members(dom, groups, name)
        if name in cell or dist.fixed is not None:
            v: Any = cell.get(name, dist.fixed)
            v = v if (dims == 1 or isinstance(v, list)) else [v] * dims
            out[name] = v if members is None else {m: v for m in members}
            continue
        if members is None:
            vals = dist.draw(sample_rng(cfg.dataset.master_seed, index, name), dims)
            out[name] = vals[0] if dims == 1 else vals
            continue
        drawn = {m: dist.draw(sample_rng(cfg.dataset.master_seed, index, f"{name}:{m}"), dims) for m in members}
        out[name] = {m: (v[0] if dims == 1 else v) for m, v in drawn.items()}
    return out


def _members(dom: Domain, groups: dict[str, Sequence[str]] | None, name: str) -> list[str] | None:
    """The members a ``per`` quantity is drawn for (None: one value per sample)."""
    if not dom.per:
        return None
    given = (groups or {}).get(dom.per)
    if given is None and dom.per == "channel":
        from scopetwin.scenes.cmu.layout import CHANNEL_NAMES

        given = CHANNEL_NAMES
    if given is None:
        raise DatasetError(
            f"key vary.{name}: drawn per {dom.per}; the {dom.per} names come from the setup (use Plan.parameters)"
        )
    return list(given)


def sweep_size(cfg: DatasetConfig) -> int:
    """Number of cells of the sweep grid (1 without sweeps)."""
    return int(np.prod([len(d.sweep) for _, d in cfg.vary.items() if d.sweep is not None] or [1]))
