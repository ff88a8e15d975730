"""Agent mode: the ``[[poll]]`` blocks, each resolved through the routes to its line and
slave, and what ``[polling]`` says about them (the status unit, the most blocks).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .. import schema
from ..core.status_unit import STATUS_LINE
from ..schema import Table
from .model import LineConfig, PollConfig, PollingConfig, Route
from .reading import Checker, read_scalars

#: The most items one read may ask for, by function (the application protocol's limits).
_READ_LIMITS = {1: 2000, 2: 2000, 3: 125, 4: 125}


def build_polling(
    check: Checker,
    raw: Mapping[str, Any],
    routes: Mapping[int, Route],
    lines: tuple[LineConfig, ...],
) -> PollingConfig:
    prefix = "polling."
    table = check.entry(Table.POLLING, check.table(raw, "polling"), prefix)
    config = PollingConfig(**read_scalars(check, Table.POLLING, table, prefix, ()))
    if config.status_unit and config.status_unit in routes:
        route = routes[config.status_unit]
        check.fail(
            f"{prefix}status_unit",
            f"unit {config.status_unit} is routed to line "
            f"{route.line!r}; choose an unrouted unit id (248-255 are never routed by "
            "--serial) or 0 for off",
        )
    if config.status_unit and any(line.name == STATUS_LINE for line in lines):
        check.fail(
            f"lines.{STATUS_LINE}",
            f"the status unit's answers are counted as line {STATUS_LINE!r}; rename the "
            "line, or set polling.status_unit = 0",
        )
    return config


def build_polls(
    check: Checker, raw: Mapping[str, Any], routes: Mapping[int, Route], polling: PollingConfig
) -> tuple[PollConfig, ...]:
    """The ``[[poll]]`` blocks, each resolved to its line and slave through the routes."""
    entries = raw.get("poll", [])
    if not isinstance(entries, list):
        check.fail("poll", "write [[poll]] tables with unit, function, address, count, every")
        return ()
    if len(entries) > polling.max_blocks:
        check.fail(
            "poll",
            f"{len(entries)} blocks, more than polling.max_blocks = "
            f"{polling.max_blocks}; merge blocks or raise polling.max_blocks",
        )
    blocks: list[PollConfig] = []
    for index, entry in enumerate(entries):
        prefix = f"poll[{index}]."
        if not isinstance(entry, dict):
            check.fail(f"poll[{index}]", "must be a table with unit, function, address, count")
            continue
        entry = check.entry(Table.POLL, entry, prefix)
        for required in ("unit", "count"):
            if required not in entry:
                check.fail(
                    f"{prefix}{required}", "missing; " + schema.key(Table.POLL, required).help
                )
        if "unit" not in entry or "count" not in entry:
            continue
        values = read_scalars(check, Table.POLL, entry, prefix, ())
        function, address, count = values["function"], values["address"], values["count"]
        if count is None or values["unit"] is None:
            continue  # out of its range: said already
        limit = _READ_LIMITS[function]
        if count > limit:
            items = "bits" if function in (1, 2) else "registers"
            check.fail(
                f"{prefix}count",
                f"{count} is more than function {function} reads at "
                f"once ({limit} {items}); split the block in two",
            )
            continue
        if address + count > 65536:
            check.fail(
                f"{prefix}count",
                f"address {address} + count {count} runs past 65535; lower count or address",
            )
            continue
        every = values["every"]
        max_age = values["max_age"] if values["max_age"] is not None else 3.0 * every
        if max_age < every:
            check.fail(
                f"{prefix}max_age",
                f"{max_age:g} s is shorter than every = {every:g} s: "
                "the block would be stale between polls; set max_age >= every",
            )
            continue
        route = routes.get(values["unit"])
        if route is None:
            check.fail(
                f"{prefix}unit",
                f"unit {values['unit']} is not routed; add it to a "
                "line's units or a [[routes]] entry, or poll a routed unit",
            )
            continue
        block = PollConfig(
            values["unit"], function, address, count, every, max_age, route.line, route.slave, index
        )
        for other in blocks:
            if (
                (other.line, other.slave, other.function) == (block.line, block.slave, function)
                and other.address < address + count
                and address < other.address + other.count
            ):
                check.fail(
                    f"{prefix}address",
                    f"the block overlaps poll[{other.index}] "
                    f"({other.label}) on the same slave and function; make them "
                    "adjacent or merge them",
                )
                break
        else:
            blocks.append(block)
    return tuple(blocks)
