"""A one-bounce mirror integrator for the deflectometry scenes (thesis §1.6.5).

The plugin ``scopetwin_mirror`` follows a camera ray to its first surface:

* an emitter (the pattern or calibration target) seen directly: its radiance;
* a perfect mirror (a BSDF with a delta-reflection lobe: the substrate's ROI, the flat
  mirror): the ray is reflected about the shading normal, r_out = r_in - 2 (r_in.N) N
  (eq. 1.7), and the radiance of the emitter it reaches is returned;
* anything else (the holding-frame regions, nothing at all): black.

The reflected ray starts at ``si.p + eps*r_out``, i.e. *along* the reflected ray, not
offset along the normal as Mitsuba's ``spawn_ray`` does: the normal offset moves the
reflected ray by up to a few µm on the pattern (0.025 px RMS centroid error, docs/rendering.md),
the offset along the ray moves nothing. The mirror reflectance is 1.

The trace itself is :mod:`scopetwin.scenes.mitsuba.trace`, shared with the renderer that traces only the pixels
that can see a marker (:mod:`scopetwin.scenes.mitsuba.lit`).
"""

from __future__ import annotations

from typing import Any

from scopetwin.scenes.mitsuba.variant import register_plugin, resolve

PLUGIN = "scopetwin_mirror"

#: Default start offset of reflected rays along their own direction, mm (1 µm: far above the
#: float32 rounding of hit points, ~2 nm here, and far below any scene feature).
DEFAULT_EPS = 1e-3


def integrator_dict(eps: float = DEFAULT_EPS, variant: str | None = None) -> dict[str, Any]:
    """Scene-dictionary entry of the mirror integrator (registered for ``variant``, default ``choose("mono")``)."""
    register(variant)
    return {"type": PLUGIN, "eps": float(eps)}


def _make_class(mi: Any) -> type:
    from scopetwin.scenes.mitsuba.trace import MirrorScene, mirror_scene, radiance

    class MirrorIntegrator(mi.SamplingIntegrator):
        """Emitter seen directly or in one perfect specular reflection; black elsewhere."""

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.eps = float(props.get("eps", DEFAULT_EPS))
            self._geometry: tuple[int, MirrorScene] | None = None

        def geometry(self, scene: mi.Scene) -> MirrorScene:
            """The trace's view of ``scene`` (:func:`scopetwin.scenes.mitsuba.trace.mirror_scene`), built once."""
            if self._geometry is None or self._geometry[0] != scene.ptr:
                self._geometry = (scene.ptr, mirror_scene(mi, scene, self.eps))
            return self._geometry[1]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            value, seen = radiance(self.geometry(scene), scene, mi.Ray3f(ray), active)
            return mi.Spectrum(value), seen, []

        def aov_names(self) -> list[str]:
            return []

        def to_string(self) -> str:
            return f"MirrorIntegrator[eps={self.eps}]"

    return MirrorIntegrator


def register(variant: str | None = None) -> None:
    """Register ``scopetwin_mirror`` for ``variant`` (default ``choose("mono")``) in this thread (idempotent)."""
    register_plugin("integrator", PLUGIN, _make_class, resolve(variant, "mono"))
