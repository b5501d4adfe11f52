"""The repository stands alone: it cites its own documentation, never notes kept outside it.

* No tracked file refers to notes kept outside the repository (design or rendering notes, the folder beside it,
  the thesis's text file): the project's own pages in ``docs/`` say all of it.
* ``docs/contract.md`` has every section that code and users cite by name, and every section of
  ``docs/contract.md`` or ``docs/rendering.md`` that a tracked file cites by its quoted name exists.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"

#: Strings no tracked file may contain (spelled in pieces, so that this file does not contain them itself).
FORBIDDEN = ("DESIGN" + ".md", "../" + "shared", "shared/" + "seeds", "NOTES" + "-rendering")

#: The sections of the contract, with their heading level: code and the README cite them by these names.
CONTRACT_SECTIONS = [
    ("##", "Units"),
    ("##", "Frames"),
    ("##", "Camera"),
    ("##", "Marker indices"),
    ("##", "Files"),
    ("###", "Images"),
    ("###", "Height maps"),
    ("###", "Truth"),
    ("###", "Datasets"),
    ("##", "Command line"),
    ("##", "Scale"),
    ("##", "Rig files"),
    ("##", "Emulators"),
]


def _tracked_files() -> list[Path]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the tracked files are unknown")
    out = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60
    ).stdout.decode()
    return [ROOT / name for name in out.split("\0") if name]


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file or one that is gone from the working tree."""
    try:
        data = path.read_bytes()
    except (FileNotFoundError, IsADirectoryError):
        return None
    if b"\0" in data:
        return None
    return data.decode("utf-8", errors="replace")


def _headings(page: Path) -> list[tuple[str, str]]:
    """(level, title) of every Markdown heading of ``page``, outside fenced code blocks."""
    found: list[tuple[str, str]] = []
    fenced = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"^(#{1,6})\s+(.+?)\s*$", line)):
            found.append((m.group(1), m.group(2).strip("`")))
    return found


def test_no_tracked_file_points_outside_the_repository() -> None:
    offenders = []
    for path in _tracked_files():
        text = _text(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            for word in FORBIDDEN:
                if word in line:
                    offenders.append(f"{path.relative_to(ROOT)}:{number}: {word}")
    assert not offenders, "cite docs/ instead:\n" + "\n".join(offenders)


def test_the_contract_has_every_section_cited_by_name() -> None:
    headings = _headings(DOCS / "contract.md")
    missing = [f"{level} {title}" for level, title in CONTRACT_SECTIONS if (level, title) not in headings]
    assert not missing, f"docs/contract.md lacks the section(s): {missing}"
    # the subsections of "Files" lie inside it, before "Command line"
    order = [title for _, title in headings]
    files, command_line = order.index("Files"), order.index("Command line")
    assert all(files < order.index(sub) < command_line for sub in ("Images", "Height maps", "Truth", "Datasets"))


def test_every_cited_docs_section_exists() -> None:
    pages = {name: {title for _, title in _headings(DOCS / name)} for name in ("contract.md", "rendering.md")}
    cite = re.compile(r"docs/(contract|rendering)\.md,\s*[\"']([^\"']+)[\"']")
    unknown = []
    for path in _tracked_files():
        text = _text(path)
        if text is None:
            continue
        for m in cite.finditer(text):
            page, section = f"{m.group(1)}.md", m.group(2)
            if section not in pages[page]:
                unknown.append(f"{path.relative_to(ROOT)}: docs/{page}, {section!r}")
    assert not unknown, "cited sections that the docs do not have:\n" + "\n".join(unknown)
