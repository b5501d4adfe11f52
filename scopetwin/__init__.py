"""scopetwin: a physically based testbed for the optics of a microscopy thesis.

The package's layers are its subpackages: :mod:`scopetwin.scenes` (the physical world and its renders),
:mod:`scopetwin.recon` (from images to surfaces), :mod:`scopetwin.calib` (from images to setup parameters),
:mod:`scopetwin.instrument` (devices and rigs) and :mod:`scopetwin.sim` (synthetic truth, studies, the command line).
"""

from scopetwin._version import __version__

__all__ = ["__version__"]
