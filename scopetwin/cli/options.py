"""Argparse ``type=`` functions for the numeric options: finite, positive, in range; the options and
help layout every command shares (:func:`conventions`).

Each factory returns a converter that argparse calls with the option's text; a value that is not a number, not
finite, or out of range raises :class:`argparse.ArgumentTypeError`, which argparse prints as one line naming the
option (``scopetwin optics grin: error: argument --spp: must be an integer >= 1, got '0'``) and exit code 2 —
before any work starts.

>>> positive_int()("16")
16
>>> finite_float(lo=0.0)("-1")
Traceback (most recent call last):
...
argparse.ArgumentTypeError: must be a finite number >= 0, got '-1'
"""

from __future__ import annotations

import argparse
import itertools
import math
from collections.abc import Callable
from typing import Any

#: Largest pixel count accepted for an image side (``--width``, ``--height``): beyond it the render estimate of
#: :func:`scopetwin.scenes.limits.check_render` refuses the request anyway, this only stops absurd numbers early.
MAX_SIDE_PX = 1_000_000
#: Largest samples-per-pixel accepted (2^31 - 1: Mitsuba's samplers count samples in 32-bit integers).
MAX_SPP = 2**31 - 1
#: Largest seed accepted (Mitsuba's samplers take a 32-bit seed).
MAX_SEED = 2**32 - 1


def _num(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def _bounds(lo: float | None, hi: float | None, lo_open: bool = False) -> str:
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {_num(lo)}")
    if hi is not None:
        parts.append(f"<= {_num(hi)}")
    return " and ".join(parts)


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """Converter to an integer in [lo, hi] (either bound may be None)."""
    what = "an integer" + (f" {_bounds(lo, hi)}" if lo is not None or hi is not None else "")

    def convert(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    convert.__name__ = "integer"
    return convert


def positive_int(hi: int | None = None) -> Callable[[str], int]:
    """Converter to an integer >= 1 (and <= ``hi``)."""
    return int_range(1, hi)


def nonnegative_int(hi: int | None = None) -> Callable[[str], int]:
    """Converter to an integer >= 0 (and <= ``hi``)."""
    return int_range(0, hi)


def finite_float(lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Callable[[str], float]:
    """Converter to a finite float in [lo, hi] (``lo_open``: > lo); ``inf`` and ``nan`` are refused."""
    bounds = _bounds(lo, hi, lo_open)
    what = "a finite number" + (f" {bounds}" if bounds else "")

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        bad = not math.isfinite(value)
        bad = bad or (lo is not None and (value <= lo if lo_open else value < lo))
        bad = bad or (hi is not None and value > hi)
        if bad:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    convert.__name__ = "number"
    return convert


def positive_float(hi: float | None = None) -> Callable[[str], float]:
    """Converter to a finite float > 0 (and <= ``hi``)."""
    return finite_float(0.0, hi, lo_open=True)


def finite_vector(n: int = 3, nonzero: bool = True) -> Callable[[str], tuple[float, ...]]:
    """Converter of ``"X,Y,Z"`` to ``n`` finite floats (``nonzero``: not all 0)."""
    what = f"{n} finite numbers separated by commas" + (", not all 0" if nonzero else "")

    def convert(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        if len(vals) != n or not all(math.isfinite(v) for v in vals) or (nonzero and not any(vals)):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return vals

    convert.__name__ = "vector"
    return convert


#: The common ones.
SPP = positive_int(MAX_SPP)
SIDE_PX = positive_int(MAX_SIDE_PX)
SEED = nonnegative_int(MAX_SEED)


def add_cluster_options(p: argparse.ArgumentParser) -> None:
    """``--scheduler`` / ``--workers`` / ``--threads``: where a dataset or a study runs (docs/contract.md, "Scale")."""
    p.add_argument("--scheduler", metavar="ADDRESS", help="existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--workers",
        type=nonnegative_int(1024),
        metavar="N",
        help="local worker processes (default: one per core; 0: no Dask, work in this process)",
    )
    p.add_argument(
        "--threads",
        type=positive_int(1024),
        metavar="N",
        help="Dr.Jit threads per worker (default 1 on a local cluster)",
    )


# -- what every (sub)command shares --------------------------------------------------------------------
#: Attribute holding the top level's ``-v`` count; a sub-command level counts in ``verbose.N`` (see common_options).
VERBOSE = "verbose"
_LEVELS = itertools.count(1)


def common_options(top: bool = False) -> argparse.ArgumentParser:
    """A parent parser with ``-v/--verbose`` (repeatable) and ``-q/--quiet`` for one parser of the command tree.

    Every parser of the tree gets its own (``parents=[common_options()]``, :func:`conventions`), so the options work
    before and after any command word: ``scopetwin -v reconstruct ...`` and ``scopetwin reconstruct ... -v``. argparse
    parses a sub-command into a fresh namespace and copies it over its parent's, which would reset a count made
    above it; so each sub-level counts ``-v`` in an attribute of its own (``verbose.1``, ``verbose.2``, ...; the
    top level in ``verbose``) and :func:`verbosity` adds them up. ``quiet`` is one flag: below the top level its
    default is suppressed, so a sub-command leaves the top level's ``-q`` standing.
    """
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument(
        "-v",
        "--verbose",
        action="count",
        dest=VERBOSE if top else f"{VERBOSE}.{next(_LEVELS)}",
        default=0 if top else argparse.SUPPRESS,
        help="log what the command does on stderr (-vv: debugging detail too)",
    )
    p.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=False if top else argparse.SUPPRESS,
        help="errors only: no warnings, notes or progress bars",
    )
    return p


def verbosity(args: argparse.Namespace) -> int:
    """How many ``-v`` were given, at any level of the command (see :func:`common_options`)."""
    return sum(int(v) for k, v in vars(args).items() if k == VERBOSE or k.startswith(f"{VERBOSE}."))


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help text: a description's or epilog's paragraphs wrapped to the terminal, indented lines (the
    ``examples:`` command lines) kept as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        lines: list[str] = []
        paragraph: list[str] = []

        def flush() -> None:
            if paragraph:
                lines.append(argparse.HelpFormatter._fill_text(self, " ".join(paragraph), width, indent))
                paragraph.clear()

        for line in text.splitlines():
            if line.strip() and not line[0].isspace():
                paragraph.append(line)
                continue
            flush()
            lines.append(indent + line if line.strip() else "")
        flush()
        return "\n".join(lines)


def conventions(*examples: str, note: str | None = None) -> dict[str, Any]:
    """Keyword arguments of ``add_parser`` that every parser of the command tree takes.

    ``-v``/``-q`` (:func:`common_options`), the :class:`HelpFormatter`, and an epilog ending in ``examples:`` and
    the command lines given, one per line, indented (each one that works with the shipped presets, rigs and
    examples); ``note``, a paragraph before them.
    """
    epilog = ([note, ""] if note else []) + ["examples:"] + [f"  {e}" for e in examples]
    return {"parents": [common_options()], "formatter_class": HelpFormatter, "epilog": "\n".join(epilog)}
