"""``[policies.NAME]``: the rule lists listeners refer to by name, read into the core's
``Rule`` (what each rule grants is decided in ``core/policy.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..core import pdu as fc
from ..core.policy import Access, Rule, merge_ranges
from .reading import Checker, networks

_ACCESS = {"read": Access.READ, "write": Access.WRITE, "read_write": Access.READ_WRITE}


_RULE_KEYS = {"role", "source", "units", "line", "slave", "functions", "addresses", "access"}


def build_policies(check: Checker, raw: Mapping[str, Any]) -> dict[str, tuple[Rule, ...]]:
    table = check.table(raw, "policies")
    policies: dict[str, tuple[Rule, ...]] = {}
    for name, body in table.items():
        key = f"policies.{name}"
        if not isinstance(body, dict):
            check.fail(key, "must be a table; write rules as [[policies.NAME.rules]]")
            continue
        check.unknown_keys(body, {"rules"}, f"{key}.")
        entries = body.get("rules", [])
        if not isinstance(entries, list):
            check.fail(f"{key}.rules", "write rules as [[policies.NAME.rules]] tables")
            continue
        rules = [_build_rule(check, entry, f"{key}.rules[{i}]") for i, entry in enumerate(entries)]
        policies[name] = tuple(rule for rule in rules if rule is not None)
    return policies


def _build_rule(check: Checker, entry: Any, key: str) -> Rule | None:
    if not isinstance(entry, dict):
        check.fail(
            key,
            "must be a table with role, source, units, line, slave, functions, addresses, access",
        )
        return None
    prefix = f"{key}."
    check.unknown_keys(entry, _RULE_KEYS, prefix)
    role = entry.get("role")
    if role is not None and (not isinstance(role, str) or not role):
        check.fail(f"{prefix}role", 'write the role as a non-empty string, like "operator"')
        role = None
    units = _rule_numbers(check, entry, "units", prefix, 0, 255, "0 is broadcast, 1..255 unit ids")
    slaves = _rule_numbers(check, entry, "slave", prefix, 1, 247, "slave addresses 1..247")
    functions: frozenset[tuple[int, int | None]] | None = None
    if "functions" in entry:
        raw_functions = entry["functions"]
        if not isinstance(raw_functions, list):
            raw_functions = [raw_functions]
        keys = set()
        for item in raw_functions:
            try:
                keys.add(parse_function_key(item))
            except ValueError as error:
                check.fail(f"{prefix}functions", str(error))
        functions = frozenset(keys)
    addresses = None
    if "addresses" in entry:
        try:
            addresses = merge_ranges(_ranges(entry["addresses"], 0, 65535))
        except ValueError as error:
            check.fail(f"{prefix}addresses", str(error))
    access = _ACCESS[check.choice(entry, "access", prefix, "read_write", tuple(_ACCESS))]
    return Rule(
        key=key,
        role=role,
        sources=networks(check, entry, "source", prefix),
        units=units,
        functions=functions,
        addresses=addresses,
        access=access,
        lines=_rule_lines(check, entry, prefix),
        slaves=slaves,
    )


def parse_function_key(item: Any) -> tuple[int, int | None]:
    """``3``, ``"0x10"``, ``"write_single_register"``, ``"8:4"`` or ``"diagnostics:0"``.

    FC 8 takes a subfunction (0..65535), FC 43 a MEI type (0..255); raise ValueError with the fix.
    """
    if isinstance(item, int) and not isinstance(item, bool):
        if not 1 <= item <= 127:
            raise ValueError(f"function code {item} outside 1..127")
        return item, None
    if not isinstance(item, str):
        raise ValueError(f"{item!r} is not a function code or name")
    text, sep, sub_text = item.strip().lower().partition(":")
    code = next((c for c, name in fc.FUNCTION_NAMES.items() if name == text), None)
    if code is None:
        try:
            code = int(text, 0)
        except ValueError:
            raise ValueError(
                f"{item!r} is not a function: write a code (3), a name (read_holding_registers) "
                'or "8:4" for a diagnostics subfunction'
            ) from None
        if not 1 <= code <= 127:
            raise ValueError(f"function code {code} outside 1..127")
    if not sep:
        return code, None
    limit = {fc.DIAGNOSTICS: 0xFFFF, fc.ENCAPSULATED_INTERFACE: 0xFF}.get(code)
    try:
        sub = int(sub_text, 0)
    except ValueError:
        sub = -1
    if limit is None or not 0 <= sub <= limit:
        raise ValueError(
            f"{item!r}: only diagnostics (8:0..65535) and encapsulated_interface (43:0..255) "
            "take a subfunction after the colon"
        )
    return code, sub


def _ranges(value: Any, low: int, high: int) -> list[tuple[int, int]]:
    """``[0, "100-199"]`` as inclusive ranges; ValueError with the fix."""
    if isinstance(value, int | str) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, list):
        raise ValueError(f'write a list of numbers and ranges, like [{low}, "{low + 10}-{high}"]')
    spans: list[tuple[int, int]] = []
    for item in value:
        if isinstance(item, int) and not isinstance(item, bool):
            first = last = item
        elif isinstance(item, str) and "-" in item:
            first_text, _, last_text = item.partition("-")
            if not (first_text.strip().isdigit() and last_text.strip().isdigit()):
                raise ValueError(f'{item!r} is not a range like "{low}-{high}"')
            first, last = int(first_text), int(last_text)
        elif isinstance(item, str) and item.strip().isdigit():
            first = last = int(item)
        else:
            raise ValueError(f"{item!r} is not a number or a range")
        if not (low <= first <= last <= high):
            raise ValueError(f"{item!r} outside {low}..{high} (or backwards)")
        spans.append((first, last))
    return spans


def _rule_numbers(
    check: Checker, entry: Mapping[str, Any], key: str, prefix: str, low: int, high: int, what: str
) -> frozenset[int] | None:
    """A rule's ``units`` or ``slave``: numbers and ranges; ``None`` when not written."""
    if key not in entry:
        return None
    try:
        spans = _ranges(entry[key], low, high)
    except ValueError as error:
        check.fail(f"{prefix}{key}", f"{error} ({what})")
        return None
    return frozenset(number for first, last in spans for number in range(first, last + 1))


def _rule_lines(check: Checker, entry: Mapping[str, Any], prefix: str) -> frozenset[str] | None:
    """A rule's ``line``: one line name or a list of them; ``None`` when not written."""
    if "line" not in entry:
        return None
    value = entry["line"]
    names = [value] if isinstance(value, str) else value
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        check.fail(f"{prefix}line", 'write a line name or a list of them, like "a" or ["a", "b"]')
        return None
    return frozenset(names)
