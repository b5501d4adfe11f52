"""``python -m scopetwin.cli ...``: the ``scopetwin`` command line (:func:`scopetwin.cli.console_main`)."""

import sys

from scopetwin.cli import console_main

sys.exit(console_main())
