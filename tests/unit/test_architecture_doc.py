"""docs/architecture.md's module table names every module of ``gateway/``, and only those.

A row's first cell names modules by path (``gateway/core/crc.py``), a package by its folder
(``gateway/io/pair/``: every module in it), and more modules of the same folder by their
file names after the first path (``gateway/core/admission.py``, ``routes.py``). A module
added, moved or removed without its row fails here, naming the row to write.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "architecture.md"
#: Files that hold no code of their own to describe: package markers and entry points.
NOT_MODULES = {"__init__.py", "__main__.py"}


def table_rows(text: str) -> list[str]:
    """The first cell of every row of the table headed ``| module | owns |``."""
    lines = text.splitlines()
    start = lines.index("| module | owns |") + 2
    rows: list[str] = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append(line.split("|")[1])
    return rows


def named(cell: str) -> set[str]:
    """The paths one cell names, each file name resolved against the path before it."""
    paths: set[str] = set()
    folder = ""
    for word in re.findall(r"`([^`]+)`", cell):
        if "/" in word:
            folder = word if word.endswith("/") else word.rpartition("/")[0] + "/"
            paths.add(word)
        else:
            paths.add(folder + word)
    return paths


def modules() -> set[str]:
    found = set()
    for path in (ROOT / "gateway").rglob("*.py"):
        if path.name not in NOT_MODULES:
            found.add(path.relative_to(ROOT).as_posix())
    return found


def test_the_resolution_of_a_cell() -> None:
    assert named("`gateway/core/admission.py`, `routes.py`") == {
        "gateway/core/admission.py",
        "gateway/core/routes.py",
    }
    assert named("`gateway/io/pair/`") == {"gateway/io/pair/"}


def test_every_module_has_its_row_and_every_row_its_module() -> None:
    listed = set().union(*map(named, table_rows(PAGE.read_text())))
    packages = {path for path in listed if path.endswith("/")}
    files = listed - packages
    present = modules()
    covered = {m for m in present if m in files or any(m.startswith(p) for p in packages)}
    missing = sorted(present - covered)
    assert not missing, f"docs/architecture.md: add a row (| `path` | what it owns |) for {missing}"
    gone = sorted(p for p in files if not (ROOT / p).is_file())
    gone += sorted(p for p in packages if not (ROOT / p).is_dir())
    assert not gone, f"docs/architecture.md names modules that are not there: {gone}"
