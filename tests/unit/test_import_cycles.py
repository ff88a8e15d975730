"""No import cycle inside ``gateway/``: each module can be read knowing only what it imports.

The graph holds the imports a module makes when it is loaded: those at module level,
including inside ``try``/``if`` blocks, but not those under ``if TYPE_CHECKING:`` (types
only) nor those inside a function (run later, on demand). Between the line driver and the
redundancy pair, every import counts: type-only ones, those inside functions, and the
``__init__`` of each package an import passes through.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import gateway

PACKAGE = Path(gateway.__file__).parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _load_time_imports(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """The import statements run when the module loads (not in functions, not type-only)."""
    for node in body:
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _load_time_imports(node.body)
            yield from _load_time_imports(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, node.orelse, node.finalbody):
                yield from _load_time_imports(block)
            for handler in node.handlers:
                yield from _load_time_imports(handler.body)
        elif isinstance(node, ast.With):
            yield from _load_time_imports(node.body)


def _targets(module: str, is_package: bool, node: ast.Import | ast.ImportFrom) -> set[str]:
    """The ``gateway`` modules an import statement loads (a package or a module in it)."""
    if isinstance(node, ast.Import):
        return {alias.name for alias in node.names}
    if node.level:
        package = module if is_package else module.rpartition(".")[0]
        for _ in range(node.level - 1):
            package = package.rpartition(".")[0]
        base = f"{package}.{node.module}" if node.module else package
    else:
        base = node.module or ""
    return {base} | {f"{base}.{alias.name}" for alias in node.names}


def _any_imports(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement, type-only and inside functions included."""
    for node in ast.walk(ast.Module(body=body, type_ignores=[])):
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node


def _packages_of(name: str) -> set[str]:
    """The packages whose ``__init__`` importing ``name`` runs: ``a.b.c`` → ``a``, ``a.b``."""
    parts = name.split(".")
    return {".".join(parts[:end]) for end in range(1, len(parts))}


def import_graph(*, every_import: bool = False) -> dict[str, set[str]]:
    """Module → the ``gateway`` modules it imports at load time; ``every_import``: those
    it imports anywhere, and the packages each import passes through, too."""
    paths = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        tree = ast.parse(path.read_text(), str(path))
        is_package = path.name == "__init__.py"
        edges: set[str] = set()
        imports = _any_imports if every_import else _load_time_imports
        for node in imports(tree.body):
            targets = _targets(module, is_package, node)
            if every_import:
                targets |= {package for name in targets for package in _packages_of(name)}
            edges |= {name for name in targets if name in paths}
        edges.discard(module)
        graph[module] = edges
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected group of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph.get(node, ())):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def test_the_graph_sees_the_package() -> None:
    graph = import_graph()
    assert "gateway.app" in graph and "gateway.core.pdu" in graph
    assert "gateway.metrics" in graph["gateway.app"]


def test_cycles_are_found_when_present() -> None:
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_inside_the_package() -> None:
    assert find_cycles(import_graph()) == []


def _every_import(module: str) -> set[str]:
    """What ``module`` imports anywhere, type-only and function-level imports included."""
    path = PACKAGE.parent.joinpath(*module.split(".")).with_suffix(".py")
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import | ast.ImportFrom):
            targets |= _targets(module, False, node)
    return targets


def test_status_and_trace_do_not_know_the_application() -> None:
    """They read the narrow ``GatewayView`` the app provides, not the app, even for types."""
    for module in (
        "gateway.io.http.live",
        "gateway.io.status",
        "gateway.io.frame_trace",
        "gateway.trace",
        "gateway.metrics",
    ):
        assert "gateway.app" not in _every_import(module), module


DRIVER = "gateway.io.line.bus"
PAIR = "gateway.io.pair"


def _in_pair(module: str) -> bool:
    return module == PAIR or module.startswith(PAIR + ".")


def test_the_line_driver_and_the_pair_import_each_other_in_no_cycle() -> None:
    """The pair uses the driver; the driver knows the pair only through its own
    ``LineRole`` protocol, so no import of any kind leads from it back to the pair."""
    graph = import_graph(every_import=True)
    assert DRIVER in graph[f"{PAIR}.role"]  # the pair does import the driver
    assert PAIR in graph[f"{PAIR}.role"]  # and an import runs its package's __init__
    tangled = [
        group for group in find_cycles(graph) if DRIVER in group and any(map(_in_pair, group))
    ]
    assert tangled == []


LINE = "gateway.core.line"


def test_the_line_machine_and_its_parts_import_each_other_in_no_cycle() -> None:
    """Inside ``core/line`` every import counts (type-only ones, those inside functions,
    a package's ``__init__`` outside the importer's own): the wire strategies and the
    parts never import the machine, so nothing leads back to it."""
    graph = import_graph(every_import=True)
    line = {
        module: {
            target
            for target in targets
            if target.startswith(LINE + ".") or (target == LINE and not module.startswith(LINE))
        }
        for module, targets in graph.items()
        if module.startswith(LINE + ".")
    }
    assert f"{LINE}.records" in line[f"{LINE}.machine"]  # the graph sees the package
    assert find_cycles(line) == []
    for strategy in ("wire", "flights"):
        assert f"{LINE}.machine" not in line[f"{LINE}.{strategy}"]


def test_no_import_cycle_of_any_kind_inside_the_package() -> None:
    """Every import counts: type-only ones, those inside functions, and the ``__init__`` of
    each package an import passes through, except the importer's own packages (a module
    inside a package runs that package's ``__init__`` whatever it imports). Collaborators
    that need something of the module that holds them get a Protocol of their own
    (``io/line/port.PortOwner``, ``io/line/notes.NotedLine``, ``io/pair/line.PairSide``)."""
    graph = import_graph(every_import=True)
    outward = {
        module: {target for target in targets if not module.startswith(target + ".")}
        for module, targets in graph.items()
    }
    assert find_cycles(outward) == []


#: The top-level modules that read the shell's state out (the logged trace, the page's
#: model): the shell's rooms hand that state out, so they never import them.
READ_OUT = {"gateway.status", "gateway.trace"}


def test_the_shell_imports_its_shared_vocabulary_downward() -> None:
    """The records every room of ``gateway/io/`` hands out (line, slave, master and pair
    statuses) and the frame trace every listener holds live inside ``gateway/io/``: no
    module there imports ``gateway/status.py`` or ``gateway/trace.py``, not even for a
    type or inside a function."""
    graph = import_graph(every_import=True)
    upward = {
        module: sorted(targets & READ_OUT)
        for module, targets in graph.items()
        if module.startswith("gateway.io.") and targets & READ_OUT
    }
    assert upward == {}
