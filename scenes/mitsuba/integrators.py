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
    import drjit as dr

    class MirrorIntegrator(mi.SamplingIntegrator):
        """Emitter seen directly or in one perfect specular reflection; black elsewhere."""

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.eps = float(props.get("eps", DEFAULT_EPS))
            # only what is used: position, shading normal, uv (texture), the shape (mirror test)
            self.primary_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame
            self.secondary_flags = mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame

        def sample(self, scene, sampler, ray, medium=None, active=True):
            ray = mi.Ray3f(ray)
            si = scene.ray_intersect(ray, self.primary_flags, True, active)
            hit = active & si.is_valid()
            mirror = self.mirror_mask(scene, si.shape) & hit
            n = si.sh_frame.n
            wo = ray.d - 2.0 * dr.dot(ray.d, n) * n
            reflected = mi.Ray3f(dr.fma(wo, self.eps, si.p), wo, ray.time, ray.wavelengths)
            si2 = scene.ray_intersect(reflected, self.secondary_flags, False, mirror)
            # one emitter evaluation: the surface seen in the mirror, or the one seen directly
            last = dr.select(mirror, si2, si)
            seen = hit & last.is_valid()
            radiance = last.emitter(scene, seen).eval(last, seen)
            return mi.Spectrum(radiance), hit, []

        @staticmethod
        def mirror_mask(scene, shape) -> mi.Bool:
            """True where ``shape`` is one of the scene's perfect mirrors (a delta-reflection BSDF).

            The shapes are sorted out once per trace on the host, so the kernel only compares
            pointers instead of calling into every BSDF.
            """
            mask = dr.zeros(mi.Bool, dr.width(shape))
            for s in scene.shapes():
                bsdf = s.bsdf()
                if bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaReflection):
                    mask |= shape == mi.ShapePtr(s)
            return mask

        def aov_names(self) -> list[str]:
            return []

        def to_string(self) -> str:
            return f"MirrorIntegrator[eps={self.eps}]"

    return MirrorIntegrator


def register(variant: str | None = None) -> None:
    """Register ``scopetwin_mirror`` for ``variant`` (default ``choose("mono")``) in this thread (idempotent)."""
    register_plugin("integrator", PLUGIN, _make_class, resolve(variant, "mono"))
