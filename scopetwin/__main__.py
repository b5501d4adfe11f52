"""``python -m scopetwin ...``: the ``scopetwin`` command line."""

import sys

from scopetwin.cli import console_main

sys.exit(console_main())
