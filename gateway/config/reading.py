"""Reading: a TOML file into raw tables, and raw values into typed ones.

``Checker`` reads a table's keys as the schema declares them (type, range, choices, former
names) and collects every problem instead of raising, so that one ``ConfigError`` names
each fault with its key and fix. The readers of values several tables share (addresses,
unit lists, networks, a policy's name) live here too.
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .. import schema
from ..core.policy import IPNetwork
from ..schema import Key, Table, Type


class ConfigError(Exception):
    """Every problem found in one configuration, each naming file, key and fix."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = problems
        lines = "\n".join(f"  - {problem}" for problem in problems)
        super().__init__(f"{source}: {len(problems)} configuration problem(s):\n{lines}")


def parse_host_port(text: str) -> tuple[str, int]:
    """Split ``HOST:PORT`` (``[v6]:PORT`` too); raise ValueError with the fix."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not port_text.isdigit():
        raise ValueError(f"{text!r} is not HOST:PORT; write it like 0.0.0.0:502")
    port = int(port_text)
    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} outside 0..65535")
    host = host.strip("[]") or "0.0.0.0"
    return host, port


def parse_units(value: Any) -> list[int]:
    """Units as a list of ints and ``"A-B"`` ranges; raise ValueError with the fix."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list):
        raise ValueError('write units as a list, like [1, 2, "10-20"]')
    units: list[int] = []
    for item in value:
        if isinstance(item, bool):
            raise ValueError(f"{item!r} is not a unit id")
        if isinstance(item, int):
            units.append(item)
        elif isinstance(item, str) and "-" in item:
            low_text, _, high_text = item.partition("-")
            if not (low_text.strip().isdigit() and high_text.strip().isdigit()):
                raise ValueError(f'{item!r} is not a range like "10-20"')
            low, high = int(low_text), int(high_text)
            if low > high:
                raise ValueError(f"range {item!r} runs backwards")
            units.extend(range(low, high + 1))
        elif isinstance(item, str) and item.strip().isdigit():
            units.append(int(item))
        else:
            raise ValueError(f'{item!r} is not a unit id or a range like "10-20"')
    for unit in units:
        if not 1 <= unit <= 247:
            raise ValueError(f"unit {unit} outside 1..247 (0 is broadcast, 248..255 are reserved)")
    return units


class Checker:
    """Reads typed values out of raw TOML tables, collecting problems instead of raising."""

    def __init__(self) -> None:
        self.problems: list[str] = []
        self.renamed: list[str] = []
        #: A key's full name -> the former name it was written under (messages name that).
        self.written_as: dict[str, str] = {}

    def fail(self, key: str, message: str) -> None:
        self.problems.append(f"{self.written_as.get(key, key)}: {message}")

    def unknown_keys(
        self,
        table: Mapping[str, Any],
        known: set[str] | frozenset[str],
        prefix: str,
        suggest: Iterable[str] | None = None,
    ) -> None:
        """Every key not in ``known``, with the closest of ``suggest`` (default: ``known``)."""
        names = sorted(known if suggest is None else suggest)
        for key in table:
            if key not in known:
                close = difflib.get_close_matches(str(key), names, n=1, cutoff=0.6)
                if close:
                    self.fail(f"{prefix}{key}", f"unknown key; did you mean {close[0]!r}?")
                    continue
                choices = ", ".join(names)
                self.fail(f"{prefix}{key}", f"unknown key; known keys here are: {choices}")

    def entry(self, where: Table, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
        """``table`` checked against the schema's keys of ``where``, former names renamed."""
        self.unknown_keys(table, schema.known_names(where), prefix, schema.keys_of(where))
        entry = dict(table)
        for declared in schema.keys_of(where).values():
            for alias in declared.aliases:
                if alias not in entry:
                    continue
                value = entry.pop(alias)
                if declared.name in entry:
                    self.fail(
                        f"{prefix}{alias}",
                        f"is the former name of {declared.name}; keep only {declared.name}",
                    )
                    continue
                entry[declared.name] = value
                self.written_as[f"{prefix}{declared.name}"] = f"{prefix}{alias}"
                self.renamed.append(
                    f"{prefix}{alias}: the former name of {declared.name}, "
                    f"still accepted; rename it to {declared.name}"
                )
        return entry

    def read(self, key: Key, table: Mapping[str, Any], prefix: str, default: Any = None) -> Any:
        """The value of a scalar ``key``, checked against its type and range or choices."""
        fallback: Any = key.default if default is None else default
        if key.type is Type.INTEGER:
            return self.integer(table, key.name, prefix, fallback, *key.int_range())
        if key.type in (Type.SECONDS, Type.NUMBER):
            return self.number(table, key.name, prefix, fallback, *key.float_range())
        if key.type is Type.BOOLEAN:
            return self.boolean(table, key.name, prefix, fallback)
        if key.type is Type.CHOICE:
            choices = tuple(map(str, key.choices))
            upper = all(choice.isupper() for choice in choices)
            return self.choice(table, key.name, prefix, fallback, choices, upper=upper)
        if key.type is Type.ONE_OF:
            return self.one_of(table, key, prefix)
        if key.type in (Type.ADDRESS, Type.ADDRESS_OR_OFF):
            return self.address(table, key.name, prefix, fallback)
        raise TypeError(f"{key.path}: a {key.type.value} is read by its own parser")

    def optional(self, key: Key, table: Mapping[str, Any], prefix: str) -> float | None:
        """A number of seconds, or ``None`` (the default derived from others) when "auto"."""
        if key.name not in table or table[key.name] == "auto":
            return None
        return self.number(table, key.name, prefix, 0.0, *key.float_range())

    def one_of(self, table: Mapping[str, Any], key: Key, prefix: str) -> float:
        """One of the numbers ``key.choices`` (stop bits)."""
        value = table.get(key.name, key.default)
        if value not in key.choices or isinstance(value, bool):
            *most, last = (f"{choice:g}" for choice in map(float, key.choices))
            self.fail(f"{prefix}{key.name}", f"{value!r} is not {', '.join(most)} or {last}")
            return float(str(key.default))
        return float(value)

    def integer(
        self, table: Mapping[str, Any], key: str, prefix: str, default: int, low: int, high: int
    ) -> int:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(
                f"{prefix}{key}",
                f"{value!r} is not an integer; write a whole number from {low} to {high}",
            )
            return default
        if not low <= value <= high:
            self.fail(f"{prefix}{key}", f"{value} outside {low}..{high}")
            return default
        return value

    def number(
        self,
        table: Mapping[str, Any],
        key: str,
        prefix: str,
        default: float,
        low: float,
        high: float,
    ) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
            self.fail(
                f"{prefix}{key}", f"{value!r} is not a number of seconds; write e.g. {default}"
            )
            return default
        if not low <= value <= high:
            self.fail(f"{prefix}{key}", f"{value} outside {low}..{high}")
            return default
        return float(value)

    def boolean(self, table: Mapping[str, Any], key: str, prefix: str, default: bool) -> bool:
        value = table.get(key, default)
        if not isinstance(value, bool):
            self.fail(f"{prefix}{key}", f"{value!r} is not true or false")
            return default
        return value

    def choice(
        self,
        table: Mapping[str, Any],
        key: str,
        prefix: str,
        default: str,
        choices: tuple[str, ...],
        *,
        upper: bool = False,
    ) -> str:
        value = table.get(key, default)
        if not isinstance(value, str) or (value.upper() if upper else value.lower()) not in choices:
            self.fail(f"{prefix}{key}", f"{value!r} is not one of: {', '.join(choices)}")
            return default
        return value.upper() if upper else value.lower()

    def address(
        self, table: Mapping[str, Any], key: str, prefix: str, default: str
    ) -> tuple[str, int] | None:
        value = table.get(key, default)
        if not isinstance(value, str):
            self.fail(f"{prefix}{key}", f'{value!r} is not a string like "0.0.0.0:502"')
            return parse_host_port(default)
        if value.lower() == "off":
            return None
        try:
            return parse_host_port(value)
        except ValueError as error:
            self.fail(f"{prefix}{key}", str(error))
            return parse_host_port(default)

    def table(self, raw: Mapping[str, Any], key: str) -> Mapping[str, Any]:
        value = raw.get(key, {})
        if not isinstance(value, dict):
            self.fail(key, f"must be a table ([{key}]), not {type(value).__name__}")
            return {}
        return value


def read_scalars(
    check: Checker, where: Table, table: Mapping[str, Any], prefix: str, skip: Iterable[str]
) -> dict[str, Any]:
    """Every key of ``where`` not in ``skip``, read as the schema declares it."""
    values: dict[str, Any] = {}
    for declared in schema.keys_of(where).values():
        if declared.name in skip:
            continue
        if declared.default == "auto":
            values[declared.name] = check.optional(declared, table, prefix)
        else:
            values[declared.name] = check.read(declared, table, prefix)
    return values


def networks(
    check: Checker, table: Mapping[str, Any], key: str, prefix: str
) -> tuple[IPNetwork, ...]:
    """A list of addresses or CIDR networks (a single string is a list of one)."""
    raw = table.get(key, [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list):
        check.fail(f"{prefix}{key}", 'write a list of addresses or networks, like ["10.1.2.0/24"]')
        return ()
    networks: list[IPNetwork] = []
    for item in raw:
        try:
            networks.append(ipaddress.ip_network(str(item), strict=False))
        except ValueError:
            check.fail(
                f"{prefix}{key}",
                f"{item!r} is not an IP address or network; write it like "
                '"10.1.2.0/24", "192.168.1.7" or "fd00::/8"',
            )
    return tuple(networks)


def policy_name(check: Checker, table: Mapping[str, Any], prefix: str) -> str | None:
    value = table.get("policy")
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        check.fail(f"{prefix}policy", "write the name of a [policies.NAME] table, as a string")
        return None
    return value


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; raise ``ConfigError`` naming the file and the syntax fault."""
    source = str(path)
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(source, ["file not found; pass an existing file with --config"]) from None
    except PermissionError:
        raise ConfigError(
            source, ["permission denied; make the file readable by the gateway's user"]
        ) from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(source, [f"TOML syntax: {error}"]) from None
    except UnicodeDecodeError:
        raise ConfigError(source, ["not UTF-8 text; save the file as UTF-8"]) from None
    except OSError as error:  # a directory, an I/O error on the medium, ...
        raise ConfigError(source, [f"cannot read: {error.strerror or error}"]) from None
