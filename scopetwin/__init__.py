"""scopetwin: a physically based testbed for the optics of a microscopy thesis.

The front door (:mod:`scopetwin.api`) gives the main jobs in a few lines::

    import scopetwin

    m = scopetwin.render("thesis-1.10-deflectometry", spp=16, seed=1)  # image + truth
    r = scopetwin.reconstruct(m.image, m.setup)                          # heights with uncertainty
    r.height_at(0.0, 0.0), r.uncertainty.absolute_um, r.uncertainty.shape_um

The package's layers are its subpackages: :mod:`scopetwin.scenes` (the physical world and its renders),
:mod:`scopetwin.recon` (from images to surfaces), :mod:`scopetwin.calib` (from images to setup parameters),
:mod:`scopetwin.instrument` (devices and rigs) and :mod:`scopetwin.sim` (synthetic truth, studies). The command line,
:mod:`scopetwin.cli`, sits beside the front door, above the layers. ``import scopetwin`` loads none of them: each
front-door function imports what it needs when called.
"""

from scopetwin._version import __version__
from scopetwin.api import (
    Measurement,
    calibrate,
    calibrate_setup,
    load_setup,
    open_dataset,
    open_rig,
    reconstruct,
    render,
)

__all__ = [
    "Measurement",
    "__version__",
    "calibrate",
    "calibrate_setup",
    "load_setup",
    "open_dataset",
    "open_rig",
    "reconstruct",
    "render",
]
