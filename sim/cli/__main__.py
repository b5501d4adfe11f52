"""``python -m sim.cli ...``: the ``scopetwin`` command line (:func:`scopetwin.sim.cli.main`)."""

import sys

from scopetwin.sim.cli import main

sys.exit(main())
