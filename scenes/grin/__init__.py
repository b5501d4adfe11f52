"""GRIN rod-lens objectives of the miniaturised parallel microscope (thesis ch. 7-8), numpy float64 world model.

Profiles n(r, λ) (:mod:`~scopetwin.scenes.grin.profiles`), glasses (:mod:`~scopetwin.scenes.grin.glass`), the layouts of
§7.5.2, §8.3.1 and §8.3.2 as setups (:mod:`~scopetwin.scenes.grin.setup`), analytic paraxial ABCD results
(:mod:`~scopetwin.scenes.grin.paraxial`), the numpy reference RKN tracer (:mod:`~scopetwin.scenes.grin.rkn`), analysis
(spots, NA, Airy, OPD; :mod:`~scopetwin.scenes.grin.analysis`) and test targets (:mod:`~scopetwin.scenes.grin.targets`).
The Dr.Jit/Mitsuba realisation lives in :mod:`scopetwin.scenes.mitsuba.grin`.
"""

from scopetwin.scenes.grin.setup import GrinSetup, build_stack, grin_setup_from_dict, load_grin_setup, profile_override

__all__ = ["GrinSetup", "build_stack", "grin_setup_from_dict", "load_grin_setup", "profile_override"]
