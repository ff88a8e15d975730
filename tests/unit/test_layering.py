"""The protocol core stays pure: no I/O, no clock, no logging, no metrics (see the design)."""

from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "gateway" / "core"
FORBIDDEN = {"asyncio", "serial", "socket", "time", "logging", "prometheus_client", "os", "select"}


def _imported_roots(path: Path) -> set[str]:
    roots: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def test_the_core_imports_no_io_clock_logging_or_metrics() -> None:
    modules = sorted(CORE.glob("*.py"))
    assert len(modules) >= 6
    offenders = {
        path.name: sorted(_imported_roots(path) & FORBIDDEN)
        for path in modules
        if _imported_roots(path) & FORBIDDEN
    }
    assert offenders == {}
