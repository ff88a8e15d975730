"""``modbus-gateway --help`` names every subcommand the command line dispatches."""

from __future__ import annotations

import ast
import inspect

import pytest

from gateway import cli


def _dispatched() -> set[str]:
    """The words ``_subcommand`` and ``main`` compare ``argv[0]`` (or ``argv``) with."""
    found: set[str] = set()
    for function in (cli._subcommand, cli.main):
        tree = ast.parse(inspect.getsource(function).strip())
        for node in ast.walk(tree):
            if not isinstance(node, ast.Compare) or len(node.comparators) != 1:
                continue
            if ast.unparse(node.left) not in ("argv", "argv[0]"):
                continue
            compared = node.comparators[0]
            if isinstance(compared, ast.Constant) and isinstance(compared.value, str):
                found.add(compared.value)
            elif isinstance(compared, ast.List):
                found |= {
                    e.value
                    for e in compared.elts
                    if isinstance(e, ast.Constant) and isinstance(e.value, str)
                }
    return found


def test_help_names_every_subcommand_in_quotes(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "1000")  # argparse wraps at hyphens otherwise
    text = cli.build_parser().format_help()
    dispatched = _dispatched()
    assert {"check-config", "audit", "scan", "example-config", "trace"} <= dispatched
    for word in dispatched:
        assert f"'{word}" in text, f"--help does not name the {word!r} subcommand"
    assert "'audit verify FILE...'" in text
