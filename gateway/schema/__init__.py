"""The configuration schema: every key of the TOML file declared once.

Theory of operation: a ``Key`` states where it is written (its ``Table``), its type,
default, range or choices, help, what a reload does when it changes, the command-line flag
that overrides it and its former names. The parser (``gateway.config``) takes the
known-key sets, did-you-mean suggestions, defaults, ranges and choices from here; the CLI
builds its override flags and ``apply_overrides`` from the flags declared here; the example
configuration and docs/configuration.md are rendered from here (``python -m gateway.schema
--write``), and a test fails when a committed copy drifts. Nothing here parses a file.
"""

from __future__ import annotations

from collections.abc import Mapping

from .keys import KEYS
from .model import TOP_LEVEL, Flag, Key, Reload, Scope, Show, Table, Type


def keys_of(table: Table) -> Mapping[str, Key]:
    """The keys of ``table`` by name, in declaration order."""
    return _BY_TABLE[table]


def key(table: Table, name: str) -> Key:
    """One key; KeyError names it when it is not declared."""
    return _BY_TABLE[table][name]


def known_names(table: Table) -> frozenset[str]:
    """Every name ``table`` accepts: its keys and their former names."""
    return _KNOWN[table]


def flagged() -> tuple[Key, ...]:
    """The keys a command-line flag overrides, in declaration order."""
    return tuple(k for k in KEYS if k.flag is not None)


def _index() -> dict[Table, dict[str, Key]]:
    by_table: dict[Table, dict[str, Key]] = {table: {} for table in Table}
    for declared in KEYS:
        assert declared.name not in by_table[declared.table], declared.path
        by_table[declared.table][declared.name] = declared
    return by_table


_BY_TABLE = _index()
_KNOWN = {
    table: frozenset(names) | {alias for k in names.values() for alias in k.aliases}
    for table, names in _BY_TABLE.items()
}

__all__ = [
    "KEYS",
    "TOP_LEVEL",
    "Flag",
    "Key",
    "Reload",
    "Scope",
    "Show",
    "Table",
    "Type",
    "flagged",
    "key",
    "keys_of",
    "known_names",
]
