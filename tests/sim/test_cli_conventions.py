"""Command-line conventions: every command and sub-command takes -v/-q before or after its words,
ends its help with examples that parse and name shipped presets / rigs / examples, and the library logs instead of
printing."""

from __future__ import annotations

import argparse
import ast
import logging
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from scopetwin.cli import build_parser, main
from scopetwin.cli.logs import LOGGER, log_to_stderr
from scopetwin.cli.options import verbosity
from scopetwin.scenes.setup import preset_names

ROOT = Path(__file__).parents[2]
LIBRARY = ("scenes", "recon", "calib", "instrument", "sim")


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _required(parser: argparse.ArgumentParser) -> list[str]:
    """Placeholder values for the required arguments of one parser level (positionals in order, required options)."""
    argv: list[str] = []
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction | argparse._HelpAction):
            continue
        value = str(next(iter(a.choices))) if a.choices else "1"
        if not a.option_strings and a.nargs not in ("*", "?"):
            argv += [value] * (a.nargs if isinstance(a.nargs, int) else 1)
        elif a.option_strings and a.required:
            argv += [a.option_strings[-1], value]
    return argv


def _walk(parser: argparse.ArgumentParser, words: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], list[str]]]:
    """Every (sub)command below ``parser``: its command words and an argv that reaches it with minimal arguments,
    as (words, [argv per level]) so options can go between the levels."""
    sub = _subparsers(parser)
    if sub is None:
        return
    for name, child in sub.choices.items():
        yield from _walk_child(child, (*words, name))


def _walk_child(parser: argparse.ArgumentParser, words: tuple[str, ...]) -> Iterator[tuple[tuple[str, ...], list]]:
    yield words, [parser]
    sub = _subparsers(parser)
    if sub is not None:
        for name, child in sub.choices.items():
            for w, parsers in _walk_child(child, (*words, name)):
                yield w, [parser, *parsers]


def _commands() -> list[tuple[tuple[str, ...], list[argparse.ArgumentParser]]]:
    return list(_walk(build_parser()))


def _levels(words: tuple[str, ...], parsers: list[argparse.ArgumentParser]) -> list[list[str]]:
    """argv pieces, one per level: the command word then that level's required arguments."""
    return [[w, *_required(p)] for w, p in zip(words, parsers, strict=True)]


def _leaves() -> list[tuple[tuple[str, ...], list[argparse.ArgumentParser]]]:
    return [(w, ps) for w, ps in _commands() if _subparsers(ps[-1]) is None]


COMMANDS = _commands()
LEAVES = _leaves()


def test_the_walk_sees_every_nested_command():
    names = {" ".join(w) for w, _ in COMMANDS}
    expected = {"render", "presets", "run", "markers", "reconstruct", "calibrate", "calibrate-setup", "study"}
    expected |= {"emulate", "dataset", "dataset generate", "dataset resume", "dataset verify", "optics"}
    expected |= {"optics grin", "optics cmu", "optics scan", "rig", "rig info", "rig move", "rig position"}
    expected |= {"rig acquire", "rig mda", "rig serve"}
    assert expected <= names


@pytest.mark.parametrize("words,parsers", COMMANDS, ids=[" ".join(w) for w, _ in COMMANDS])
def test_every_parser_has_verbose_and_quiet(words, parsers):
    options = {s for a in parsers[-1]._actions for s in a.option_strings}
    assert {"-v", "--verbose", "-q", "--quiet"} <= options, words


@pytest.mark.parametrize("words,parsers", LEAVES, ids=[" ".join(w) for w, _ in LEAVES])
def test_every_command_takes_v_and_q_before_between_and_after_its_words(words, parsers):
    parser = build_parser()
    levels = _levels(words, parsers)
    flat = [x for level in levels for x in level]

    args = parser.parse_args(flat)
    assert verbosity(args) == 0 and args.quiet is False
    assert verbosity(parser.parse_args([*flat, "-v"])) == 1
    assert verbosity(parser.parse_args([*flat, "-vv"])) == 2
    assert verbosity(parser.parse_args(["-v", *flat])) == 1
    assert verbosity(parser.parse_args(["-v", *flat, "--verbose"])) == 2  # counts add up across the levels
    assert parser.parse_args([*flat, "-q"]).quiet is True
    assert parser.parse_args(["--quiet", *flat]).quiet is True  # a sub-command does not reset the top level's -q
    if len(levels) > 1:  # between the words of a nested command: scopetwin dataset -v generate ...
        between = [*levels[0], "-v", "-q", *[x for level in levels[1:] for x in level]]
        args = parser.parse_args(between)
        assert verbosity(args) == 1 and args.quiet is True


def test_v_and_q_together_are_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["presets", "-v", "-q"])
    assert exc.value.code == 2
    assert "-v/--verbose and -q/--quiet exclude each other" in capsys.readouterr().err


def _examples(parser: argparse.ArgumentParser) -> list[str]:
    lines = parser.format_help().rstrip().splitlines()
    assert "examples:" in lines, parser.prog
    block = lines[len(lines) - 1 - lines[::-1].index("examples:") + 1 :]
    return [line.strip() for line in block]


@pytest.mark.parametrize("words,parsers", COMMANDS, ids=[" ".join(w) for w, _ in COMMANDS])
def test_every_help_ends_with_one_or_two_examples(words, parsers):
    parser = parsers[-1]
    assert parser.formatter_class is not argparse.HelpFormatter
    examples = _examples(parser)
    assert 1 <= len(examples) <= 2, (words, examples)
    assert all(e.startswith("scopetwin ") for e in examples), examples
    raw = parser.epilog or ""
    assert all(f"  {e}" in raw.splitlines() for e in examples), "the examples are printed as written, not wrapped"


def _example_commands() -> list[tuple[str, str]]:
    out = []
    for words, parsers in [((), [build_parser()]), *COMMANDS]:
        for line in _examples(parsers[-1]):
            for command in line.split(";"):
                out.append((" ".join(words) or "scopetwin", command.strip()))
    return out


EXAMPLES = _example_commands()


@pytest.mark.parametrize("where,command", EXAMPLES, ids=[f"{w}: {c}" for w, c in EXAMPLES])
def test_every_example_parses_and_names_shipped_files(where, command):
    argv = shlex.split(command)
    assert argv[0] == "scopetwin"
    if argv[1:] == ["COMMAND", "--help"]:
        return
    build_parser().parse_args(argv[1:])  # SystemExit (exit 2) on an example that does not parse
    presets = set(preset_names())
    for token in argv[1:]:
        if token.startswith("thesis-"):
            assert token in presets, f"{where}: unknown preset {token}"
        if token.startswith(("rigs/", "examples/")):
            assert (ROOT / token).is_file(), f"{where}: {token} is not shipped"


def test_quiet_hides_and_verbose_shows_info_on_stderr(capsys):
    assert main(["presets"]) == 0
    captured = capsys.readouterr()
    assert "thesis-1.10-deflectometry" in captured.out and captured.err == ""  # default: warnings only

    assert main(["presets", "-v"]) == 0
    captured = capsys.readouterr()
    assert "thesis-1.10-deflectometry" in captured.out  # the result is the same
    assert "scopetwin: presets finished in " in captured.err and "debug" not in captured.err

    assert main(["-vv", "presets"]) == 0
    err = capsys.readouterr().err
    assert "scopetwin: debug: scopetwin.cli: presets: arguments" in err and "finished in" in err

    assert main(["-q", "presets"]) == 0
    captured = capsys.readouterr()
    assert "thesis-1.10-deflectometry" in captured.out and captured.err == ""
    assert not logging.getLogger(LOGGER).handlers  # main leaves no handler behind


def test_levels_and_format_of_library_loggers(capsys):
    library = logging.getLogger("scopetwin.recon.example")
    for verbosity_, quiet, shown in [(0, False, {"warning", "error"}), (1, False, {"info", "warning", "error"})]:
        with log_to_stderr(verbosity_, quiet):
            library.debug("d")
            library.info("i")
            library.warning("w")
            library.error("e")
        err = capsys.readouterr().err.splitlines()
        expected = {
            "info": "scopetwin: i",
            "warning": "scopetwin: warning: w",
            "error": "scopetwin: error: e",
        }
        assert err == [expected[k] for k in ("info", "warning", "error") if k in shown]
    with log_to_stderr(2, False):
        library.debug("d")
    assert capsys.readouterr().err == "scopetwin: debug: scopetwin.recon.example: d\n"
    with log_to_stderr(0, True):
        library.warning("w")
        library.error("e")
    assert capsys.readouterr().err == "scopetwin: error: e\n"


def test_v_and_q_in_a_separate_process():
    def run(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "scopetwin.cli", *argv], capture_output=True, text=True, timeout=120, cwd=ROOT
        )

    loud, quiet = run("presets", "--verbose"), run("presets", "--quiet")
    assert loud.returncode == 0 and quiet.returncode == 0
    assert loud.stdout == quiet.stdout and "thesis-cmu" in loud.stdout
    assert "scopetwin: presets finished in " in loud.stderr and quiet.stderr == ""


def _library_files() -> list[Path]:
    """The layers' modules and the top package's own (the front door): all but the command line, scopetwin/cli/."""
    files = [p for d in LIBRARY for p in sorted((ROOT / d).rglob("*.py"))]
    return files + sorted((ROOT / "scopetwin").glob("*.py"))


def _prints(path: Path, root: Path = ROOT) -> list[str]:
    """Calls of print() and traceback.print_exc / print_exception / print_stack in one module."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id in ("print", "print_exc", "print_exception", "print_stack"):
            found.append(f"{path.relative_to(root)}:{node.lineno}: {ast.unparse(node)[:80]}")
        elif (
            isinstance(f, ast.Attribute)
            and isinstance(f.value, ast.Name)
            and f.value.id == "traceback"
            and f.attr.startswith("print")
        ):
            found.append(f"{path.relative_to(root)}:{node.lineno}: {ast.unparse(node)[:80]}")
    return found


def test_library_modules_log_and_never_print():
    files = _library_files()
    assert len(files) > 50 and any(p.name == "pipeline.py" for p in files)
    found = [line for p in files for line in _prints(p)]
    assert not found, "library modules log through logging.getLogger(__name__), never print:\n" + "\n".join(found)


def test_the_print_finder_finds_prints(tmp_path):
    sample = tmp_path / "m.py"
    sample.write_text("import traceback\nprint('x')\ntraceback.print_exc()\nlog.info('fine')\n")
    assert len(_prints(sample, tmp_path)) == 2


def test_an_unknown_option_of_a_command_lists_every_command(capsys):
    """The parser built for one command knows its own group only; argparse's error shows the whole command list."""
    with pytest.raises(SystemExit) as stop:
        main(["presets", "--bogus"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: --bogus" in err
    usage = err.split("scopetwin: error:")[0]
    commands = _subparsers(build_parser())
    assert commands is not None and len(commands.choices) >= 12
    assert all(name in usage for name in commands.choices), usage
