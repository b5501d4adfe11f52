"""The illumination path of thesis §7.5.3 (Fig. 7.10, 7.11), unfolded at the 45° beam splitter.

Unfolded, the excitation light runs along +z: the square Lambertian LED (0.5 mm, 488 nm, 1 mW) at
z = 0; air (``led_distance``, 2.427 mm); the illumination GRIN rod (``rod_length``, 2.369 mm, the
GrinTech profile of the objective's rod 1); half of the beam-splitter layer; the reflection at the
splitter (a factor ``splitter_reflectance``); the other half; the object-side substrate; rod 1 of
the objective traversed backwards; the object gap; the cover glass, whose far face (where the cells
lie, §7.5.2) is the object plane and the end of the stack. The layout of
Fig. 7.10 is not given in numbers beyond the two optimised values, so the unfolded order is an
assumption (stated in the report).

Losses: Fresnel reflection at every interface up to the object plane at normal incidence,
(n1-n2)²/(n1+n2)² (unpolarised, a lower bound on the oblique loss), times the splitter reflectance.
What §7.5.3 calls the "energy efficiency" (about 33 %) is not defined further; the readings and their
numbers are in :func:`scopetwin.scenes.mitsuba.grin.illuminate`.
"""

from __future__ import annotations

from scopetwin.scenes.grin.glass import AIR, Glass
from scopetwin.scenes.grin.setup import GrinSetup, IlluminationSpec, Layer, RodSpec, Stack


def illumination_stack(setup: GrinSetup, spec: IlluminationSpec | None = None) -> Stack:
    """Unfolded illumination layers, LED plane at z = 0, object plane at the end (the stack's image plane).

    The last layer is the cover glass: its far face is the object plane. (An earlier version ended the
    stack with a zero-thickness air layer, which put two Mitsuba planes at the same z; which one a ray
    met first then depended on the BVH order, and most rays were lost at random, per process.)
    """
    ill = spec or setup.illumination or IlluminationSpec()
    lam = ill.wavelength_nm
    img = setup.stack(wavelength_nm=lam)
    by_name = {layer.name: layer for layer in img.layers}
    rod_ill = RodSpec(
        length=ill.rod_length, radius=setup.rod1.radius, profile=setup.rod1.profile, step_mm=setup.rod1.step_mm
    )
    rod1 = setup.rod1 if ill.rod1_length is None else setup.rod1.model_copy(update={"length": ill.rod1_length})
    half_bs = 0.5 * setup.beam_splitter.thickness
    bs = by_name["beam_splitter"]
    seq: list[tuple[str, Glass, float, RodSpec | None]] = [
        ("led_gap", AIR, ill.led_distance, None),
        ("rod_illumination", AIR, rod_ill.length, rod_ill),
        ("splitter_in", bs.glass, half_bs, None),
        ("splitter_out", bs.glass, half_bs, None),
    ]
    # the object-side part of the imaging stack, in reverse (towards the object)
    obj_part = [layer for layer in img.layers if layer.name in ("cover", "object_gap", "rod1", "substrate1")]
    for layer in reversed(obj_part):
        rod = rod1 if layer.rod is not None else None
        seq.append((layer.name, layer.glass, rod.length if rod else layer.thickness, rod))
    layers = []
    z = 0.0
    for name, gl, t, rod in seq:
        profile = rod.profile.at(lam) if rod is not None else None
        layers.append(Layer(name, z, z + t, gl, gl.index(lam), rod, profile))
        z += t
    return Stack(tuple(layers), lam, 0.0, -1.0, None)


def fresnel_transmission(stack: Stack) -> float:
    """Product of normal-incidence Fresnel transmissions over the stack's interfaces (rods: their axial index)."""
    idx = [layer.profile.n0 if layer.profile is not None else layer.index for layer in stack.layers]
    t = 1.0
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        t *= 1.0 - ((a - b) / (a + b)) ** 2
    return t
