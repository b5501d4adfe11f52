"""A useq MDA plan read, sized and checked against the rig's limits before anything moves.

Optional dependency: ``pip install scopetwin[mm]`` (useq-schema). Nothing here enumerates the events of a
plan: its sizes (time points, positions, grid points, channels, z planes), its number of planes, bytes and
least duration come in closed form from the plans' parameters, so a 1e8-loop time plan or a 1e9 µm z range is
sized in microseconds. :func:`check_plan` checks every stage position (grid extents included), every z plane
(the z plan around each position, plus each channel's ``z_offset``), every exposure and every channel preset
against :class:`PlanLimits`, and raises :class:`~scopetwin.instrument.errors.RigError` with one line naming
the event and the limit at the first that is out of range.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from scopetwin.instrument.devices import Range
from scopetwin.instrument.errors import OutOfRangeError, RigError
from scopetwin.scenes.inputs import InputError, load_structured_input, validation_line
from scopetwin.shipped import find_input

#: The grid plans sized and checked in closed form (their rows, columns and offsets follow from their fields).
RECTANGULAR_GRIDS = ("GridRowsColumns", "GridWidthHeight", "GridFromEdges")


def _useq() -> Any:
    try:
        import useq
    except ImportError as exc:  # pragma: no cover - optional extra
        raise RigError("MDA needs useq-schema: pip install 'scopetwin[mm]'") from exc
    return useq


def load_sequence(sequence: Any) -> Any:
    """A ``useq.MDASequence`` from a sequence, a dict, or a YAML / JSON file path (µm and ms)."""
    useq = _useq()
    if isinstance(sequence, useq.MDASequence):
        return sequence
    try:
        if isinstance(sequence, Mapping):
            return useq.MDASequence(**sequence)
    except Exception as exc:  # noqa: BLE001 - pydantic's validation errors
        raise RigError(f"bad MDA sequence: {validation_line(exc)}") from None
    path = find_input(sequence)  # a documented examples/mda/... path reads the shipped sequence from any folder
    try:  # a regular file of at most 16 MiB nested at most 64 levels; one line for what useq refuses
        return useq.MDASequence.model_validate(load_structured_input(path, "MDA sequence"))
    except InputError as exc:
        raise RigError(str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - pydantic's validation errors
        raise RigError(f"MDA sequence {str(path)!r}: {validation_line(exc)}") from None


@dataclass(frozen=True)
class PlanLimits:
    """What the rig allows an MDA, and where its devices are now (µm, ms).

    Attributes
    ----------
    x_um, y_um, z_um : Range or None
        Travel of the XY stage's axes and the focus range; ``None`` where the core has no such device.
    exposure_ms : Range
        The camera's exposure range.
    frame_shape : tuple of int
        ``(rows, cols)`` of a frame.
    pixel_size_um : float
        Size of a pixel on the sample (sets the field of view of grid plans).
    bytes_per_pixel : int
        Bytes of a pixel in the buffer (2 for 12-bit frames).
    channel_group : str
        The core's channel group.
    presets : dict
        Preset name -> ``{(device, property): value}`` of the channel group.
    check_setting : callable, optional
        ``(device, property, value) -> None``: raises ``ValueError`` naming the limit when a preset's value is out of
        the property's limits or allowed values.
    now_um : tuple
        ``(x, y, z)`` where the stages and the focus are now (``None`` without the device).
    exposure_now_ms : float
        The camera's exposure now (channels without an exposure keep it).
    """

    x_um: Range | None
    y_um: Range | None
    z_um: Range | None
    exposure_ms: Range
    frame_shape: tuple[int, int]
    pixel_size_um: float
    bytes_per_pixel: int = 2
    channel_group: str = "Channel"
    presets: Mapping[str, Mapping[tuple[str, str], str]] | None = None
    check_setting: Callable[[str, str, str], None] | None = None
    now_um: tuple[float | None, float | None, float | None] = (None, None, None)
    exposure_now_ms: float = 10.0


@dataclass(frozen=True)
class PlanSize:
    """A plan's size in closed form.

    Attributes
    ----------
    sizes : dict
        Axis -> count (``t``, ``p``, ``g``, ``c``, ``z``; 0 where the axis is unused). ``g`` is the grid points of
        all positions together (``p`` x grid points for a shared grid).
    planes : int
        Frames the plan takes.
    bytes : int
        Bytes of those frames.
    seconds : float
        Least duration: the longer of the time plan's span and the sum of the exposures (moves and readout come on top).
    """

    sizes: dict[str, int]
    planes: int
    bytes: int
    seconds: float


# -- sizes in closed form --------------------------------------------------------------------------------------------
def _timepoints(plan: Any) -> tuple[int, float]:
    """(time points, span in s) of a time plan without iterating it."""
    if plan is None:
        return 0, 0.0
    phases = getattr(plan, "phases", None)
    if phases is not None:  # MultiPhaseTimePlan: later phases share their first point with the end of the previous
        parts = [_timepoints(phase) for phase in phases]
        return max(0, sum(n for n, _ in parts) - (len(parts) - 1)), sum(s for _, s in parts)
    loops = int(plan.loops)
    # a plan whose duration is a field (duration + interval) gives it; where it is a property (loops x interval)
    # it is computed here in float — useq's own timedelta product overflows for a huge loop count
    if not isinstance(getattr(type(plan), "duration", None), property) and getattr(plan, "duration", None) is not None:
        return loops, float(plan.duration.total_seconds())
    return loops, float(plan.interval.total_seconds()) * max(0, loops - 1)


def _z_count(plan: Any) -> int:
    """z planes of a z plan, from its range and step (never :func:`numpy.arange`)."""
    if plan is None:
        return 0
    if hasattr(plan, "absolute") or hasattr(plan, "relative"):
        return len(getattr(plan, "absolute", None) or getattr(plan, "relative", None) or ())
    return int(plan.num_positions())


def _z_span(plan: Any) -> tuple[float, float] | None:
    """(lowest, highest) z of a z plan: offsets from the position's z when relative, absolute otherwise."""
    if plan is None:
        return None
    values = getattr(plan, "absolute", None) or getattr(plan, "relative", None)
    if values is not None:
        return (min(values), max(values)) if len(values) else None
    start, stop, step = plan._start_stop_step()
    if step == 0:
        return start, start
    return start, start + (plan.num_positions() - 1) * step


def _fov(grid: Any, limits: PlanLimits) -> Any:
    rows, cols = limits.frame_shape
    return grid.model_copy(update={"fov_width": cols * limits.pixel_size_um, "fov_height": rows * limits.pixel_size_um})


def _grid_extent(grid: Any, limits: PlanLimits) -> tuple[int, tuple[float, float, float, float]]:
    """(points, (x low, x high, y low, y high)) of a grid plan in closed form; offsets when it is relative."""
    name = type(grid).__name__
    if name == "RandomPoints":
        half_w, half_h = grid.max_width / 2, grid.max_height / 2
        return int(grid.num_points), (-half_w, half_w, -half_h, half_h)
    if name not in RECTANGULAR_GRIDS:
        raise RigError(
            f"grid plan {name} is not supported (sized and checked: {', '.join(RECTANGULAR_GRIDS)}, RandomPoints)"
        )
    grid = _fov(grid, limits)
    dx, dy = grid._step_size(grid.fov_width, grid.fov_height)
    rows, cols = grid._nrows(dy), grid._ncolumns(dx)
    x0, y0 = grid._offset_x(dx), grid._offset_y(dy)
    return rows * cols, (x0, x0 + (cols - 1) * dx, y0 - (rows - 1) * dy, y0)


def _positions(seq: Any) -> list[Any]:
    """The stage positions (a one-element list of ``None`` without any: the stage stays where it is)."""
    positions = list(seq.stage_positions)
    return positions or [None]


def _grid_of(seq: Any, position: Any) -> Any:
    sub = getattr(position, "sequence", None)
    return sub.grid_plan if sub is not None and sub.grid_plan is not None else seq.grid_plan


def plan_size(seq: Any, limits: PlanLimits) -> PlanSize:
    """The plan's sizes, planes, bytes and least duration, in closed form (no event is made)."""
    nt, span_s = _timepoints(seq.time_plan)
    nz = _z_count(seq.z_plan)
    grids = [_grid_of(seq, position) for position in _positions(seq)]
    grid_points = sum(_grid_extent(grid, limits)[0] if grid is not None else 1 for grid in grids)
    n_positions = len(seq.stage_positions)
    channels = list(seq.channels) or [None]
    planes, exposure_s = 0, 0.0
    for channel in channels:
        t = math.ceil(max(nt, 1) / (channel.acquire_every if channel is not None else 1))
        z = max(nz, 1) if channel is None or channel.do_stack else 1
        exposure = channel.exposure if channel is not None and channel.exposure is not None else limits.exposure_now_ms
        planes += grid_points * t * z
        exposure_s += grid_points * t * z * exposure * 1e-3
    sizes = {"t": nt, "p": n_positions, "g": grid_points if any(grid is not None for grid in grids) else 0}
    sizes |= {"c": len(seq.channels), "z": nz}
    rows, cols = limits.frame_shape
    return PlanSize(sizes, planes, planes * rows * cols * limits.bytes_per_pixel, max(span_s, exposure_s))


# -- checks against the rig ------------------------------------------------------------------------------------------
def _check_structure(seq: Any) -> None:
    """Refuse what the checks (and the OME writers' regular arrays) cannot represent, before anything else."""
    for index, position in enumerate(seq.stage_positions):
        sub = getattr(position, "sequence", None)
        if sub is not None and (sub.time_plan or sub.channels or sub.z_plan):
            raise RigError(f"MDA position p={index} has its own time, channel or z plan: only a grid plan is supported")
    for index, channel in enumerate(seq.channels):
        if seq.z_plan is not None and not channel.do_stack:
            raise RigError(f"MDA channel c={index} ({channel.config!r}): do_stack=false is not supported")
        if channel.acquire_every != 1:
            raise RigError(
                f"MDA channel c={index} ({channel.config!r}): acquire_every={channel.acquire_every} is not supported"
            )
    if seq.grid_plan is not None and seq.stage_positions and "g" in seq.axis_order and "p" in seq.axis_order:
        if abs(seq.axis_order.index("p") - seq.axis_order.index("g")) != 1:
            raise RigError(f"MDA axis_order {''.join(seq.axis_order)!r}: p and g must be next to each other")


def _check_channels(seq: Any, limits: PlanLimits) -> None:
    """Each channel: a preset of the channel group whose settings are in range, and an exposure in range."""
    presets = limits.presets or {}
    for index, channel in enumerate(seq.channels):
        event = f"MDA event c={index} (channel {channel.config!r})"
        if channel.group != limits.channel_group:
            raise RigError(f"{event}: group {channel.group!r} is not the channel group {limits.channel_group!r}")
        if channel.config not in presets:
            raise RigError(
                f"{event}: no preset {channel.config!r} in group {channel.group!r}; presets: {sorted(presets)}"
            )
        for (device, prop), value in presets[channel.config].items():
            if limits.check_setting is not None:
                try:
                    limits.check_setting(device, prop, value)
                except ValueError as exc:
                    raise RigError(f"{event}: preset sets {device}-{prop} = {value!r}: {exc}") from exc
        exposure = channel.exposure if channel.exposure is not None else limits.exposure_now_ms
        _in(limits.exposure_ms, exposure, f"{event}: exposure")


def _in(allowed: Range | None, value: float, what: str) -> None:
    if allowed is None:
        raise RigError(f"{what}: the core has no device for it")
    try:
        allowed.check(value, what)
    except OutOfRangeError as exc:
        raise RigError(str(exc)) from exc


def _z_offsets(seq: Any) -> tuple[float, float]:
    offsets = [float(channel.z_offset) for channel in seq.channels] or [0.0]
    return min(offsets), max(offsets)


def _check_position(seq: Any, index: int, position: Any, limits: PlanLimits) -> None:
    """The stage positions (with the grid's extent) and z planes of one stage position."""
    event = f"MDA event p={index}" if position is not None else "MDA event"
    x = position.x if position is not None and position.x is not None else limits.now_um[0]
    y = position.y if position is not None and position.y is not None else limits.now_um[1]
    grid = _grid_of(seq, position)
    xs, ys = [x], [y]
    if grid is not None:
        _, (x_low, x_high, y_low, y_high) = _grid_extent(grid, limits)
        relative = getattr(grid, "is_relative", True)
        xs = [x_low, x_high] if not relative else [None if x is None else x + x_low, None if x is None else x + x_high]
        ys = [y_low, y_high] if not relative else [None if y is None else y + y_low, None if y is None else y + y_high]
        event += " (grid)"
    for value, axis, allowed in [(v, "x", limits.x_um) for v in xs] + [(v, "y", limits.y_um) for v in ys]:
        if value is not None and (position is not None and getattr(position, axis) is not None or grid is not None):
            _in(allowed, value, f"{event}: stage {axis}")
    _check_z(seq, event, position, limits)


def _check_z(seq: Any, event: str, position: Any, limits: PlanLimits) -> None:
    z = position.z if position is not None and position.z is not None else limits.now_um[2]
    span = _z_span(seq.z_plan)
    low, high = _z_offsets(seq)
    if span is None and (position is None or position.z is None) and low == high == 0.0:
        return  # the focus stays where it is
    low_z, high_z = span if span is not None else (0.0, 0.0)
    relative = seq.z_plan is None or seq.z_plan.is_relative
    base = (z if z is not None else 0.0) if relative else 0.0
    for value in (base + low_z + low, base + high_z + high):
        _in(limits.z_um, value, f"{event}: focus z")


def check_plan(sequence: Any, limits: PlanLimits) -> PlanSize:
    """Check every position, z plane, exposure and channel preset of ``sequence`` against ``limits``; its size.

    Raises
    ------
    RigError
        One line naming the first event out of range and the limit (``MDA event p=1: stage x: 1e+12 um is outside
        [0.0, 150000.0] um``), or a plan the checks cannot size.
    """
    seq = load_sequence(sequence)
    _check_structure(seq)
    _check_channels(seq, limits)
    for index, position in enumerate(_positions(seq)):
        _check_position(seq, index, position, limits)
    return plan_size(seq, limits)
