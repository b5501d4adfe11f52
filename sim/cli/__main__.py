"""``python -m sim.cli ...``: the ``scopetwin`` command line (:func:`scopetwin.sim.cli.console_main`)."""

import sys

from scopetwin.sim.cli import console_main

sys.exit(console_main())
