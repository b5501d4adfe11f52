"""``python -m scopetwin ...``: the ``scopetwin`` command line."""

import sys

from scopetwin.sim.cli import main

sys.exit(main())
