"""The one place where scopetwin chooses and sets the Mitsuba variant.

Nothing sets a variant at import time: every builder and renderer of :mod:`scopetwin.scenes.mitsuba` takes a
``variant`` argument (default :func:`choose` of its kind, resolved at call time by :func:`resolve`) and
sets it for the call with :func:`mitsuba`; plugins are registered per variant by :func:`register_plugin`.

Order of choice: the environment variable ``SCOPETWIN_MI_VARIANT`` if set;
otherwise ``cuda_ad_*`` when a CUDA device is usable, else ``llvm_ad_*``
(``mono`` for the monochrome setups, ``spectral`` for the spectral microscope).
The LLVM variants need a shared LLVM library of version 16 or newer (see
docs/rendering.md); when it is missing the error says what to install.
"""

from __future__ import annotations

import ctypes.util
import functools
import glob
import os
import sys
import threading
from collections.abc import Callable
from typing import Any, Literal

from scopetwin.scenes.errors import ScopetwinError

Kind = Literal["mono", "spectral", "rgb"]
ENV_VARIANT = "SCOPETWIN_MI_VARIANT"
_lock = threading.Lock()


class MitsubaUnavailable(ScopetwinError, RuntimeError):
    """Mitsuba or the LLVM library it needs is missing."""


def _llvm_library() -> str | None:
    """Path of a shared LLVM library >= 16, or None."""
    return _find_llvm(os.environ.get("DRJIT_LIBLLVM_PATH"))


@functools.lru_cache(maxsize=4)
def _find_llvm(pinned: str | None) -> str | None:
    """The file-system search behind :func:`_llvm_library` (cached: it costs tens of ms)."""
    if pinned and os.path.exists(pinned):
        return pinned
    for version in range(25, 15, -1):
        for pattern in (
            f"/usr/lib/*/libLLVM-{version}.so*",
            f"/usr/lib/*/libLLVM.so.{version}*",
            f"/usr/lib/llvm-{version}/lib/libLLVM*.so*",
        ):
            hits = sorted(glob.glob(pattern))
            if hits:
                return hits[0]
    return None  # (ctypes' find_library("LLVM") may name LLVM 15, which drjit cannot use)


@functools.lru_cache(maxsize=1)
def _cuda_available() -> bool:
    return ctypes.util.find_library("cuda") is not None


def choose(kind: Kind = "mono") -> str:
    """Name of the variant scopetwin would use for ``kind`` on this machine."""
    forced = os.environ.get(ENV_VARIANT)
    if forced:
        return forced
    backend = "cuda" if _cuda_available() else "llvm"
    return f"{backend}_ad_{kind}"


def resolve(variant: str | None, kind: Kind = "mono") -> str:
    """The variant a builder or renderer runs in: ``variant`` if given, else :func:`choose` (resolved now)."""
    return variant if variant else choose(kind)


def unavailable(variant: str) -> str | None:
    """Why ``variant`` cannot run on this machine (what to install), or None when it can; sets no variant."""
    if variant.startswith("llvm") and _llvm_library() is None:
        return (
            "Mitsuba's llvm variants need a shared LLVM library >= 16 and none was found: "
            "install it with `apt-get install -y libllvm19` (or set DRJIT_LIBLLVM_PATH)"
        )
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - mitsuba is a hard dependency
        return f"mitsuba is not installed: {exc}"
    if variant not in mi.variants():
        return f"Mitsuba variant {variant!r} is not available; have {mi.variants()}"
    return None


def mitsuba(variant: str) -> Any:
    """Set ``variant`` in this thread (if it is not set already) and return the ``mitsuba`` module.

    The one helper every builder and renderer of :mod:`scopetwin.scenes.mitsuba` calls with its explicit variant;
    nothing
    relies on whatever variant happens to be current. A ``cuda_*`` variant that cannot start (no usable GPU)
    falls back to the matching ``llvm_*`` one.

    Raises
    ------
    MitsubaUnavailable
        If Mitsuba is not installed, the variant is unknown, or the LLVM
        library is missing (the message names the package to install).
    """
    mi_loaded = sys.modules.get("mitsuba")
    if mi_loaded is not None and mi_loaded.variant() == variant:
        return mi_loaded
    name = variant
    reason = unavailable(name)
    if reason is not None:
        raise MitsubaUnavailable(reason)
    import mitsuba as mi

    with _lock:
        if mi.variant() != name:
            if name.startswith("cuda"):
                try:
                    mi.set_variant(name)
                except Exception:  # no usable GPU after all: fall back to LLVM
                    mi.set_variant(name.replace("cuda", "llvm", 1))
            else:
                mi.set_variant(name)
    return mi


def set_thread_count(n: int) -> None:
    """Number of Dr.Jit worker threads of the LLVM backend (one per Dask worker process on a local cluster)."""
    import drjit as dr

    dr.set_thread_count(int(n))


_plugin_classes: dict[tuple[str, str], type] = {}
_plugin_done = threading.local()


def register_plugin(kind: str, name: str, make_class: Callable[[Any], type], variant: str) -> None:
    """Register the Python plugin ``name`` of ``kind`` (``integrator``, ``sensor``, ``bsdf``, ...) for ``variant``.

    Sets ``variant`` in this thread (:func:`mitsuba`). Mitsuba's Python plugin registry is per thread and per
    variant (docs/rendering.md), so the registration is remembered per thread and variant; the plugin class,
    built by ``make_class(mi)`` against that variant's base classes, is built once per variant.
    """
    mi = mitsuba(variant)
    key = (mi.variant(), name)
    done = getattr(_plugin_done, "keys", None)
    if done is None:
        done = _plugin_done.keys = set()
    if key in done:
        return
    cls = _plugin_classes.get(key)
    if cls is None:
        cls = _plugin_classes[key] = make_class(mi)
    getattr(mi, f"register_{kind}")(name, lambda props: cls(props))
    done.add(key)


class RenderInterruptedError(ScopetwinError, RuntimeError):
    """Mitsuba cancelled a render (its SIGINT handler): the image is incomplete and must not be used."""


def render_complete(mi: Any, scene: Any, **kwargs: Any) -> Any:
    """``mi.render(scene, **kwargs)``, refusing a render that Mitsuba cut short.

    During a render Mitsuba installs its own SIGINT handler, which cancels the integrator ("Received interrupt
    signal, winding down..") and hands the signal on — also in a Dask worker that ignores SIGINT, where the signal
    then goes nowhere and ``mi.render`` returns a partially rendered image. A cancelled render is therefore turned
    into :class:`RenderInterruptedError` here, so no sample or image is ever written from it. (In the main process
    Python's own handler, which Mitsuba hands the signal back to, raises KeyboardInterrupt right after the render;
    a worker's task simply fails, quietly, without the traceback a KeyboardInterrupt would print there.)
    """
    image = mi.render(scene, **kwargs)
    if scene.integrator().should_stop():
        raise RenderInterruptedError("the Mitsuba render was interrupted (SIGINT) before it finished")
    return image


def quiet_warnings(variant: str) -> None:
    """Show only Mitsuba's errors in this process (worker processes: their warnings reach no user)."""
    mi = mitsuba(variant)
    mi.set_log_level(mi.LogLevel.Error)
