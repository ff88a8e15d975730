"""The protocol core stays pure: no I/O, no clock, no logging, no metrics (see the design).

Relative imports are resolved too: ``from ..metrics import X`` inside ``gateway/core`` is
as much a breach as ``import prometheus_client``.
"""

from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "gateway" / "core"
FORBIDDEN = {"asyncio", "serial", "socket", "ssl", "time", "logging", "prometheus_client", "os",
             "select", "threading", "subprocess"}  # fmt: skip
ALLOWED_GATEWAY = "gateway.core"


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, relative imports resolved against its own package
    (``gateway.core``, or a package inside it such as ``gateway.core.line``)."""
    inside = path.parent.relative_to(CORE).parts if path.is_relative_to(CORE) else ()
    package = ["gateway", "core", *inside]
    modules: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            modules.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                modules.add(node.module or "")
                continue
            base = package[: len(package) - (node.level - 1)]
            if node.module:
                modules.add(".".join([*base, node.module]))
            else:
                modules.update(".".join([*base, alias.name]) for alias in node.names)
    return modules


def offending(modules: set[str]) -> list[str]:
    """The imports a core module must not have."""
    inside = (ALLOWED_GATEWAY, ALLOWED_GATEWAY + ".")
    return sorted(
        module
        for module in modules
        if module.split(".")[0] in FORBIDDEN
        or (module.split(".")[0] == "gateway" and not module.startswith(inside))
    )


def test_the_core_imports_no_io_clock_logging_or_metrics() -> None:
    modules = sorted(CORE.rglob("*.py"))
    assert len(modules) >= 8
    assert CORE / "line" / "machine.py" in modules  # the packages inside the core too
    offenders = {
        str(path.relative_to(CORE)): offending(imported_modules(path))
        for path in modules
        if offending(imported_modules(path))
    }
    assert offenders == {}


def test_the_check_catches_relative_imports_out_of_the_core(tmp_path: Path) -> None:
    """The check itself: a relative import of the metrics module is caught."""
    sample = tmp_path / "sample.py"
    sample.write_text("from ..metrics import UNIT_LABELS\nfrom . import pdu\nfrom .crc import x\n")
    assert offending(imported_modules(sample)) == ["gateway.metrics"]
    sample.write_text("from .. import app\nimport time\n")
    assert offending(imported_modules(sample)) == ["gateway.app", "time"]
