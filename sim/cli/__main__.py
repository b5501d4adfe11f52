"""``python -m sim.cli ...``: the ``scopetwin`` command line (:func:`sim.cli.main`)."""

import sys

from sim.cli import main

sys.exit(main())
