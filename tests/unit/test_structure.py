"""Size limits on the gateway's code: no function over 60 lines, no class over 400.

A successor reads a function whole and a class in one sitting; past these sizes the
decisions hide. Measured with ``ast`` (first line of the ``def`` or ``class`` to the last
line of its body, docstring and comments included), so formatting cannot game it.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

GATEWAY = Path(__file__).resolve().parents[2] / "gateway"
MAX_FUNCTION_LINES = 60
MAX_CLASS_LINES = 400


def _definitions() -> Iterator[tuple[str, ast.AST, int]]:
    """(``path:line name``, node, length in lines) of every function and class in gateway/."""
    for path in sorted(GATEWAY.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                end = node.end_lineno if node.end_lineno is not None else node.lineno
                where = f"{path.relative_to(GATEWAY.parent)}:{node.lineno} {node.name}"
                yield where, node, end - node.lineno + 1


def test_the_gateway_has_code_to_measure() -> None:
    assert sum(1 for _ in _definitions()) > 100


def test_no_function_over_60_lines() -> None:
    long = [
        f"{where} ({length} lines)"
        for where, node, length in _definitions()
        if not isinstance(node, ast.ClassDef) and length > MAX_FUNCTION_LINES
    ]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def test_no_class_over_400_lines() -> None:
    long = [
        f"{where} ({length} lines)"
        for where, node, length in _definitions()
        if isinstance(node, ast.ClassDef) and length > MAX_CLASS_LINES
    ]
    assert not long, f"classes over {MAX_CLASS_LINES} lines:\n" + "\n".join(long)
