"""``[[routes]]`` and each line's ``units``: where a unit id goes (a line and the slave
address on it), one line per unit.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from .. import schema
from ..schema import Table
from .model import LineConfig, Route
from .reading import Checker


def build_routes(
    check: Checker, raw: Mapping[str, Any], lines: tuple[LineConfig, ...]
) -> dict[int, Route]:
    """Each line's ``units`` (the same slave address), then every ``[[routes]]`` entry."""
    routes: dict[int, Route] = {}
    for line in lines:
        taken: dict[str, list[int]] = {}  # earlier line -> units this line repeats
        for unit in line.units:
            if unit in routes:
                taken.setdefault(routes[unit].line, []).append(unit)
                continue
            routes[unit] = Route(unit, line.name, unit)
        for other, units in taken.items():  # one message per pair of lines, as ranges
            check.fail(
                f"lines.{line.name}.units",
                f"{'unit' if len(units) == 1 else 'units'} {format_units(units)} already "
                f"routed to line {other!r}; give each unit one line",
            )
    raw_routes = raw.get("routes", [])
    if not isinstance(raw_routes, list):
        check.fail("routes", "write routes as [[routes]] tables with unit, line and slave")
        return routes
    names = {line.name for line in lines}
    for index, entry in enumerate(raw_routes):
        route = _route(check, entry, f"routes[{index}]", names)
        if route is None:
            continue
        if route.unit in routes:
            check.fail(
                f"routes[{index}].unit",
                f"unit {route.unit} is already routed to line {routes[route.unit].line!r}",
            )
            continue
        routes[route.unit] = route
    return routes


def _route(check: Checker, raw: Any, key: str, names: set[str]) -> Route | None:
    """One ``[[routes]]`` entry (``None`` when it is faulty)."""
    if not isinstance(raw, dict):
        check.fail(key, "must be a table with unit, line and slave")
        return None
    prefix = f"{key}."
    entry = check.entry(Table.ROUTES, raw, prefix)
    keys = schema.keys_of(Table.ROUTES)
    unit = check.read(keys["unit"], entry, prefix, -1) if "unit" in entry else -1
    if "unit" not in entry:
        check.fail(f"{prefix}unit", "missing; the TCP unit id (1..255) this route answers for")
    line_name = entry.get("line")
    if not isinstance(line_name, str) or line_name not in names:
        known = ", ".join(sorted(names)) or "(none defined)"
        check.fail(f"{prefix}line", f"{line_name!r} is not a configured line; lines are: {known}")
        return None
    slave = check.read(keys["slave"], entry, prefix, unit if 1 <= unit <= 247 else 1)
    return Route(unit, line_name, slave) if unit >= 1 else None


def format_units(units: Iterable[int]) -> str:
    """Unit ids as compact ranges: ``[1, 2, 3, 7, 9, 10]`` -> ``"1-3, 7, 9-10"``."""
    parts: list[str] = []
    ordered = sorted(set(units))
    start = 0
    for index, unit in enumerate(ordered):
        if index + 1 < len(ordered) and ordered[index + 1] == unit + 1:
            continue
        low = ordered[start]
        parts.append(str(low) if low == unit else f"{low}-{unit}")
        start = index + 1
    return ", ".join(parts)
