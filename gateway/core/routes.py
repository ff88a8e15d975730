"""The routing table: which line and slave address a unit id reaches (no I/O).

Theory of operation: the configuration routes each unit id a master may send
(1..255) to one ``Target``, a line name and the slave address on that line.
Several unit ids may reach one target (an *alias*: ``unit 12 → line a,
slave 2`` beside ``unit 2 → line a, slave 2``). Unit 0 is broadcast and has no
route: it goes to every line that takes broadcasts (``broadcast_lines``).

The table is pure data, built once per configuration and replaced as a whole on
reload; the io side keeps its own mapping from line name to the running line.
Admission (``core.admission``) and authorization (``core.policy``) both read it,
so a rule and a request always agree on where a unit id goes.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import NamedTuple, Protocol


class Target(NamedTuple):
    """Where a unit id goes: a line, and the slave address on it (a tuple: hashed per request)."""

    line: str
    slave: int


class RouteLike(Protocol):
    """Anything that names a line and a slave address (``config.Route``, ``Target``)."""

    @property
    def line(self) -> str: ...

    @property
    def slave(self) -> int: ...


def targets_of(routes: Mapping[int, RouteLike]) -> dict[int, Target]:
    """``{unit: Target}`` from any mapping of unit ids to routes."""
    return {unit: Target(route.line, route.slave) for unit, route in routes.items()}


class RouteTable:
    """Unit id → ``Target``, and the lines a broadcast goes to; immutable once built."""

    __slots__ = ("broadcast_lines", "routes", "units")

    def __init__(
        self, routes: Mapping[int, RouteLike], broadcast_lines: Iterable[str] = ()
    ) -> None:
        self.routes: Mapping[int, Target] = targets_of(routes)
        self.broadcast_lines: tuple[str, ...] = tuple(broadcast_lines)
        #: Each target's unit id (the lowest of its aliases): what a standby of a pair
        #: sends the active for a request this table routed there (both run one table).
        self.units: Mapping[tuple[str, int], int] = _units_of(self.routes)

    def lookup(self, unit: int) -> Target | None:
        """The target of ``unit``, ``None`` when no route serves it."""
        return self.routes.get(unit)


def _units_of(routes: Mapping[int, Target]) -> dict[tuple[str, int], int]:
    """(line, slave) → the lowest unit id routed to it."""
    units: dict[tuple[str, int], int] = {}
    for unit in sorted(routes):
        units.setdefault(routes[unit], unit)
    return units
