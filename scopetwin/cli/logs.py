"""Log messages of the command line: the ``scopetwin`` logger on stderr, at the level ``-v``/``-q`` set.

Library modules log through module loggers (``logging.getLogger(__name__)``, all under ``scopetwin.``) and never
print; :func:`scopetwin.cli.main` puts one handler on the ``scopetwin`` logger for the duration of a command:

=========  =======================  ==================================================================
option     level                    what reaches stderr
=========  =======================  ==================================================================
``-q``     ERROR                    errors only (and no progress bars)
(none)     WARNING                  warnings: ``scopetwin: warning: ...``
``-v``     INFO                     and notes on what the command does: ``scopetwin: ...``
``-vv``    DEBUG                    and debugging detail: ``scopetwin: debug: LOGGER: ...``
=========  =======================  ==================================================================

What a command prints on stdout (its result) does not depend on these options.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator
from typing import TextIO

#: The logger every module of the package logs under (``scopetwin.sim.pipeline``, ``scopetwin.recon...``).
LOGGER = "scopetwin"


def level_for(verbosity: int, quiet: bool) -> int:
    """The ``scopetwin`` logger's level: ERROR with ``quiet``, else WARNING, INFO (``-v``), DEBUG (``-vv``)."""
    if quiet:
        return logging.ERROR
    if verbosity <= 0:
        return logging.WARNING
    return logging.INFO if verbosity == 1 else logging.DEBUG


class _Stderr(logging.StreamHandler):
    """A handler writing to whatever ``sys.stderr`` is when a record arrives (tests and callers may swap it)."""

    def __init__(self) -> None:
        super().__init__()

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, value: TextIO) -> None:  # StreamHandler.__init__ assigns one: the current stderr is used
        pass


class _Format(logging.Formatter):
    """``scopetwin: MESSAGE`` for INFO; ``scopetwin: warning: MESSAGE`` (error, critical) above it;
    ``scopetwin: debug: LOGGER: MESSAGE`` below it."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if record.levelno == logging.INFO:
            return f"scopetwin: {text}"
        if record.levelno < logging.INFO:
            return f"scopetwin: debug: {record.name}: {text}"
        return f"scopetwin: {record.levelname.lower()}: {text}"


@contextlib.contextmanager
def log_to_stderr(verbosity: int = 0, quiet: bool = False) -> Iterator[logging.Logger]:
    """Within the block the ``scopetwin`` logger writes to stderr at :func:`level_for` ``(verbosity, quiet)``.

    Its level, handlers and propagation are restored afterwards, so :func:`scopetwin.cli.main` can run many
    times in one process (tests) without stacking handlers. The records do not propagate to the root logger
    meanwhile: the command line owns stderr, a message appears once.
    """
    logger = logging.getLogger(LOGGER)
    handler = _Stderr()
    handler.setFormatter(_Format("%(message)s"))
    saved = logger.level, logger.propagate
    logger.setLevel(level_for(verbosity, quiet))
    logger.propagate = False
    logger.addHandler(handler)
    try:
        yield logger
    finally:
        logger.removeHandler(handler)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
