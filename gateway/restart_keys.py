"""What a reload must not change: the keys the schema marks ``Reload.RESTART``.

The sockets, the audit file, the HTTP endpoint, the log and the pair are set up once, at
start; a reload that changes one of their keys cannot give them the new value. So the
configuration the gateway then runs with (``Gateway.config``, what the audit log records,
the reload's summary line) keeps the running value of each such key, and the key is named
as needing a restart. Which keys those are comes from the schema, not from a list here.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import fields, replace
from typing import Any, NamedTuple

from . import schema
from .config import GatewayConfig, ListenerConfig
from .schema import Key, Reload, Table

#: Keys held in fields of other names: an address is a host and a port ("off": not enabled).
_FIELDS_OF_KEY: dict[tuple[Table, str], tuple[str, ...]] = {
    (Table.SERVER, "listen"): ("host", "port"),
    (Table.METRICS, "listen"): ("enabled", "host", "port"),
    (Table.LISTENERS, "listen"): ("host", "port"),
    # A listener is known by its name; one whose protocol changed is left as it runs.
    (Table.LISTENERS, "name"): (),
    (Table.LISTENERS, "protocol"): (),
}
#: The tables written once in the file, each a field of ``GatewayConfig`` of the same name.
_SINGLE_TABLES = (Table.SERVER, Table.METRICS, Table.LOGGING, Table.AUDIT, Table.REDUNDANCY)


class Kept(NamedTuple):
    """A restart-only key a reload would have changed: its name in the file, and what holds
    it (``[server]``, ``serial-slave listener field``)."""

    owner: str
    path: str


def fields_of(key: Key) -> tuple[str, ...]:
    """The fields of its table's dataclass that hold ``key``; LookupError when none does."""
    if (key.table, key.name) in _FIELDS_OF_KEY:
        return _FIELDS_OF_KEY[key.table, key.name]
    if key.table is Table.LISTENERS:
        holder: Any = ListenerConfig
    elif key.table in _SINGLE_TABLES:
        holder = type(getattr(GatewayConfig(), key.table.value))
    else:
        raise LookupError(f"{key.path}: a reload keeps no key of {key.table.heading}")
    names = {field.name for field in fields(holder)}
    if key.name in names:
        return (key.name,)
    if key.table is Table.LISTENERS and key.only.startswith('protocol = "serial-slave"'):
        return ("serial",)  # a serial-slave listener's line: its device and format
    raise LookupError(f"{key.path}: restart-only, but no field of {holder.__name__} holds it")


def restart_keys() -> tuple[Key, ...]:
    """Every key a reload must not change, in declaration order."""
    return tuple(key for key in schema.KEYS if key.reload is Reload.RESTART)


def _keys_of(table: Table) -> Iterator[tuple[Key, tuple[str, ...]]]:
    for key in restart_keys():
        if key.table is table:
            yield key, fields_of(key)


def _keep(
    running: Any, wanted: Any, table: Table, prefix: str, owner: str
) -> tuple[Any, list[Kept]]:
    """``wanted`` with the running value of each restart-only key of ``table`` that changed."""
    values: dict[str, object] = {}
    kept: list[Kept] = []
    for key, names in _keys_of(table):
        if any(getattr(running, name) != getattr(wanted, name) for name in names):
            values.update({name: getattr(running, name) for name in names})
            kept.append(Kept(owner, prefix + key.name))
    return (replace(wanted, **values) if values else wanted), kept


def keep_restart_settings(
    running: GatewayConfig, wanted: GatewayConfig
) -> tuple[GatewayConfig, list[Kept]]:
    """``wanted`` with the running value of every restart-only key it changes, and those keys.

    A listener is known by its name. One the file adds is not opened, and one it removes or
    gives another protocol keeps running as it is: the result holds the running listeners,
    each with the file's settings when the file still has it with the same protocol, so
    that it says what runs. A running listener's policy that the file no longer has stays
    too. The app warns that those listeners need a restart.
    """
    tables: dict[str, Any] = {}
    kept: list[Kept] = []
    for table in _SINGLE_TABLES:
        name = table.value
        old, new = getattr(running, name), getattr(wanted, name)
        value, names = _keep(old, new, table, table.prefix, table.heading)
        if names:
            tables[name] = value
            kept += names
    asked = {listener.name: listener for listener in wanted.listeners}
    listeners: list[ListenerConfig] = []
    for before in running.listeners:
        listener = asked.get(before.name)
        if listener is None or listener.protocol != before.protocol:
            listeners.append(before)  # left as it runs
            continue
        owner = f"{listener.protocol} listener {listener.name}"
        listener, names = _keep(before, listener, Table.LISTENERS, listener.key_prefix, owner)
        if listener.key_prefix != "server.":  # the shorthand's address is server.listen
            kept += names
        listeners.append(listener)
    if listeners != list(wanted.listeners):
        tables["listeners"] = tuple(listeners)
        policies = dict(wanted.policies)
        for listener in listeners:
            if listener.policy is not None and listener.policy not in policies:
                policies[listener.policy] = running.policies[listener.policy]
        if policies != wanted.policies:
            tables["policies"] = policies
    return (replace(wanted, **tables) if tables else wanted), kept
