"""The compact four-channel fluorescence microscope unit (thesis ch. 3-5), numpy float64 world model.

``cmu`` is the thesis's own name for it: "one compact microscope unit (CMU)" (§3.4.1, Fig. 3.6-3.7; the
implementation §4.1, Fig. 4.1(b)).

Spectra of fluorophores, light sources, filters and dichroics (:mod:`~scopetwin.scenes.cmu.spectra`), the unit's layout
as
a setup (:mod:`~scopetwin.scenes.cmu.layout`, preset ``thesis-cmu``), bowed beam-splitter plates
(:mod:`~scopetwin.scenes.cmu.plates`), the sequential tracer with perfect lenses (:mod:`~scopetwin.scenes.cmu.trace`),
analyses
(refocus, magnification, spots, astigmatism, wavefront PSF/MTF, the 4 mm stop; :mod:`~scopetwin.scenes.cmu.analysis`)
and
the test objects (:mod:`~scopetwin.scenes.cmu.targets`), the photon budget of the four channels
(:mod:`~scopetwin.scenes.cmu.photon_budget`). The Mitsuba (spectral) realisation is :mod:`scopetwin.scenes.mitsuba.cmu`.
"""

from scopetwin.scenes.cmu.layout import CmuSetup, load_cmu_setup

__all__ = ["CmuSetup", "load_cmu_setup"]
