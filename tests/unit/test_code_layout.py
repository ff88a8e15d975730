"""The formatter lays out the code: few hand-laid tables, no file kept from ``ruff format``.

The rule (docs/contributing.md, "Code layout"): a ``# fmt: skip`` marker or a ``# fmt: off``
region is for a table whose columns carry meaning, and there are few of those.
"""

from __future__ import annotations

import ast
import io
import tokenize
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GATEWAY = ROOT / "gateway"
MOST_MARKERS = 20
#: What keeps code from the formatter: a comment that says so, written as ruff and black accept it.
MARKERS = {"fmt: skip", "fmt:skip", "fmt: off", "fmt:off"}


def formatter_markers(source: str) -> int:
    """The ``# fmt: skip`` markers and ``# fmt: off`` regions in one module's comments."""
    comments = (
        token.string.lstrip("#").strip()
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT
    )
    return sum(1 for comment in comments if comment in MARKERS)


def test_the_counter_sees_every_spelling() -> None:
    source = "x = [1,  2]  # fmt: skip\n# fmt: off\ny = 1\n# fmt: on\nz = 1  #fmt:skip\n"
    assert formatter_markers(source) == 3
    assert formatter_markers('s = "# fmt: skip"\n') == 0


def test_few_tables_are_laid_out_by_hand() -> None:
    counts = {
        path.relative_to(ROOT).as_posix(): formatter_markers(path.read_text())
        for path in sorted(GATEWAY.rglob("*.py"))
    }
    marked = {path: count for path, count in counts.items() if count}
    assert sum(marked.values()) <= MOST_MARKERS, marked


def test_no_file_is_kept_from_the_formatter() -> None:
    assert not (ROOT / "ruff.toml").exists() and not (ROOT / ".ruff.toml").exists()
    ruff = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]
    tables = {"tool.ruff": ruff, "tool.ruff.format": ruff.get("format", {})}
    for name, table in tables.items():
        kept = {key: table[key] for key in ("exclude", "extend-exclude") if key in table}
        assert not kept, f"[{name}] keeps files from ruff format: {kept}"


def test_each_class_name_is_defined_once() -> None:
    """One name, one meaning: a reader (and a grep) finds the class a name stands for."""
    defined: dict[str, list[str]] = {}
    for path in sorted(GATEWAY.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef):
                defined.setdefault(node.name, []).append(path.relative_to(ROOT).as_posix())
    twice = {name: places for name, places in defined.items() if len(places) > 1}
    assert not twice, f"give each class a name of its own: {twice}"
