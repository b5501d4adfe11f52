"""Limits from estimates: image sizes and render work checked before anything is allocated.

A request that cannot finish — a 100000 x 100000 px camera, ``spp = 1e9`` — is refused up front with one
:class:`LimitError` that gives the estimate and the limit, instead of a ``MemoryError`` or a render that runs for
weeks. Two checks:

* :func:`check_image_size` — the memory one image of ``nx`` x ``ny`` pixels needs with its working buffers,
  against this machine's physical memory (setups call it when they are loaded: such a camera can never be used
  here);
* :func:`check_render` — the same memory estimate against the memory available *now*, and the time estimate
  (rays = pixels x spp over the renderer's ray rate) against the render time limit (:func:`render_time_limit_s`:
  24 h, or ``SCOPETWIN_RENDER_LIMIT_S`` seconds).

The estimates are coarse on purpose (a factor of two either way): they exist to refuse what is far out of reach,
not to predict run times. The ray rates are the measured figures of ``docs/rendering.md`` on 2 CPU cores
(a GPU is faster, which only makes the time check conservative).
"""

from __future__ import annotations

import math
import os

from scopetwin.scenes.errors import ScopetwinError

#: 4-byte numbers held per image pixel while one image is made and written: the film (value, weight), the developed
#: image, its numpy copy, the full-size image a window is pasted into, the sensor model's float64 temporaries and the
#: preview — about 12 floats (an estimate, see the module docstring).
FLOATS_PER_PIXEL = 12
#: Fraction of the memory a single image may claim.
MEMORY_FRACTION = 0.8
#: Default render time limit, seconds (``SCOPETWIN_RENDER_LIMIT_S`` overrides it).
RENDER_LIMIT_S = 24 * 3600.0
#: Measured ray rates on 2 CPU cores (docs/rendering.md): Part I ~8e7 rays/s (1360x1024 at 64 spp in 1.1 s),
#: GRIN rods ~1e7 rays/s (float32, 36 RKN steps), the float64 numpy reference renderer ~7e5 rays/s on one core; the
#: spectral four-channel unit traces a plate stack per ray (an assumed 5e6 rays/s).
RAYS_PER_S = {"setup": 8.0e7, "analytic": 7.0e5, "grin": 1.0e7, "cmu": 5.0e6}
#: Rays in one request refused whatever the time limit (past 2^53 a float64 ray count is no longer exact).
MAX_RAYS = 2**53


class LimitError(ScopetwinError, ValueError):
    """A request whose estimated memory or time exceeds what this machine (or the configured limit) allows."""


def physical_memory() -> int:
    """Total physical memory of this machine, bytes (``os.sysconf``; 0 when it cannot be read)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 0


def available_memory() -> int:
    """Memory available to a new allocation now, bytes: psutil if installed, else /proc/meminfo, else sysconf."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover - psutil is optional
        pass
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):  # pragma: no cover - not Linux
        pass
    try:  # pragma: no cover - fallback
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 0


def render_time_limit_s() -> float:
    """The render time limit, seconds: ``SCOPETWIN_RENDER_LIMIT_S`` when set to a positive number, else 24 h."""
    text = os.environ.get("SCOPETWIN_RENDER_LIMIT_S")
    if text:
        try:
            value = float(text)
        except ValueError:
            raise LimitError(f"SCOPETWIN_RENDER_LIMIT_S must be a number of seconds, got {text!r}") from None
        if not (math.isfinite(value) and value > 0):
            raise LimitError(f"SCOPETWIN_RENDER_LIMIT_S must be a positive finite number, got {text!r}")
        return value
    return RENDER_LIMIT_S


def fmt_bytes(n: float) -> str:
    """``n`` bytes as a short text (``37.3 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover - unreachable


def fmt_seconds(s: float) -> str:
    """``s`` seconds as a short text (``3.2 h``, ``41 days``)."""
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 3 * 86400:
        return f"{s / 3600:.1f} h"
    if s < 3650 * 86400:
        return f"{s / 86400:.0f} days"
    return f"{s / (365.25 * 86400):.2g} years"


def image_bytes(nx: int, ny: int, floats_per_pixel: int = FLOATS_PER_PIXEL) -> int:
    """Estimated bytes to make and write one ``nx`` x ``ny`` image (:data:`FLOATS_PER_PIXEL` 4-byte numbers a pixel)."""
    return int(nx) * int(ny) * 4 * int(floats_per_pixel)


def check_image_size(
    nx: int, ny: int, what: str, floats_per_pixel: int = FLOATS_PER_PIXEL, memory: int | None = None
) -> None:
    """Refuse an image of ``nx`` x ``ny`` px that cannot fit in ``memory`` bytes (default: physical memory).

    ``what`` names the request in the message (``"camera.pixels"``). Raises :class:`LimitError` giving the
    estimate and the limit; does nothing when the memory cannot be read.
    """
    mem = physical_memory() if memory is None else int(memory)
    need = image_bytes(nx, ny, floats_per_pixel)
    if mem > 0 and need > MEMORY_FRACTION * mem:
        raise LimitError(
            f"{what}: a {nx} x {ny} px image needs about {fmt_bytes(need)} with its buffers "
            f"({floats_per_pixel} x 4 bytes a pixel), more than {MEMORY_FRACTION:.0%} of this machine's "
            f"{fmt_bytes(mem)} of memory"
        )


def check_render(
    nx: int,
    ny: int,
    spp: int,
    what: str,
    renderer: str = "setup",
    floats_per_pixel: int = FLOATS_PER_PIXEL,
    memory: int | None = None,
    limit_s: float | None = None,
) -> float:
    """Refuse a render of ``nx`` x ``ny`` px at ``spp`` samples per pixel that cannot finish; returns the estimate (s).

    Parameters
    ----------
    nx, ny, spp : int
        Image size and samples per pixel (each must be >= 1).
    what : str
        Names the request in the message (``"render thesis-cmu, channel blue"``).
    renderer : str
        Key of :data:`RAYS_PER_S` (``"setup"``, ``"grin"``, ``"cmu"``).
    memory : int, optional
        Bytes available (default :func:`available_memory`).
    limit_s : float, optional
        Time limit (default :func:`render_time_limit_s`).

    Raises
    ------
    LimitError
        A size or spp below 1, an image that does not fit in the memory available, or an estimated time above the
        limit — the message gives the estimate and the limit.
    """
    for name, v in (("width", nx), ("height", ny), ("spp", spp)):
        if int(v) < 1:
            raise LimitError(f"{what}: {name} must be >= 1, got {v}")
    check_image_size(nx, ny, what, floats_per_pixel, available_memory() if memory is None else memory)
    rays = float(nx) * float(ny) * float(spp)
    rate = RAYS_PER_S[renderer]
    seconds = rays / rate
    limit = render_time_limit_s() if limit_s is None else float(limit_s)
    if rays > MAX_RAYS or seconds > limit:
        raise LimitError(
            f"{what}: {nx} x {ny} px at {spp} spp is {rays:.3g} rays, about {fmt_seconds(seconds)} at "
            f"~{rate:.0e} rays/s, over the render limit of {fmt_seconds(limit)} (SCOPETWIN_RENDER_LIMIT_S seconds "
            "raises it); use fewer samples per pixel or a smaller image"
        )
    return seconds
