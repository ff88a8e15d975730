"""Plain-text tables for the terminal: right-aligned numbers, one header rule."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .scenarios import Check, Table


def _grid(columns: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    widths = [len(column) for column in columns]
    for row in rows:
        for index, cell in enumerate(row):
            widths[index] = max(widths[index], len(cell))

    def line(cells: Sequence[str]) -> str:
        parts = [
            cell.ljust(widths[index]) if index == 0 else cell.rjust(widths[index])
            for index, cell in enumerate(cells)
        ]
        return "  " + "  ".join(parts).rstrip()

    return [line(columns), "  " + "  ".join("-" * width for width in widths)] + [
        line(row) for row in rows
    ]


def render_table(table: Table) -> str:
    """The table under its title."""
    return "\n".join([table.title, *_grid(table.columns, table.rows)])


def render_checks(checks: Sequence[Check]) -> str:
    """The targets of the issues against what was measured."""
    rows = [
        [check.figure, check.measured_text(), check.target, "yes" if check.met else "NO"]
        for check in checks
    ]
    return "\n".join(["Targets", *_grid(["figure", "measured", "target", "met"], rows)])
