"""What a reload changed and what that did, in one log line an operator reads.

The keys come from the same diff the audit log records (``flatten`` and ``changed_keys``):
a key is named by its full dotted name with its old and new value, a whole line, listener
or route that came or went by its own name. What the reload did follows from the three
configurations: the running one, the one the file asked for, and the one applied (where a
setting that needs a restart keeps its running value).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from .core.audit_record import changed_keys, flatten

#: A listener's keys that bind its socket or open its serial line: a reload leaves them.
_LISTENER_RESTART_KEYS = frozenset({"protocol", "host", "port", "serial"})
#: The tables whose keys the listeners apply at a reload (policies, allow lists, TLS files).
_LISTENER_TABLES = ("server.", "listeners.", "policies.")
#: Tables whose items are named: one of them coming or going is named once.
_NAMED_TABLES = ("lines", "listeners", "routes", "policies")
#: Not a setting: where the configuration was read from.
_NOT_SETTINGS = frozenset({"source"})


def _whole_item(key: str, present: Mapping[str, str]) -> str | None:
    """``lines.b`` when ``key`` is ``lines.b.<anything>`` and ``present`` has no key of it."""
    table, _, rest = key.partition(".")
    name = rest.partition(".")[0]
    if table not in _NAMED_TABLES or not name:
        return None
    item = f"{table}.{name}"
    return None if any(k.startswith(item + ".") for k in present) else item


def _listener_restart_only(key: str) -> bool:
    """A listener's address, protocol or serial line: bound at start, kept by a reload."""
    parts = key.split(".")
    return parts[0] == "listeners" and len(parts) >= 3 and parts[2] in _LISTENER_RESTART_KEYS


def summarize(
    running: object, wanted: object, applied: object, port_settings: Iterable[str]
) -> str:
    """``lines.a.timeout 0.5 → 0.7; line a retuned`` … for the reload from ``running`` to
    ``wanted`` (the file), of which ``applied`` is what now runs."""
    before, asked, after = flatten(running), flatten(wanted), flatten(applied)
    reopening = frozenset(port_settings)
    changes: list[str] = []
    kept: list[str] = []
    items_done: set[str] = set()
    reopened: set[str] = set()
    retuned: set[str] = set()
    listeners = False
    for key in changed_keys(before, asked):
        if key in _NOT_SETTINGS:
            continue
        added, removed = _whole_item(key, before), _whole_item(key, asked)
        item = added or removed
        if item is not None:
            if item in items_done:
                continue
            items_done.add(item)
            # Not done: a listener is bound (or opened) at start only, and what a running
            # listener uses stays with it (its policy).
            restart = (_whole_item(key, after) is None) == bool(removed)
            (kept if restart else changes).append(f"{item} {'added' if added else 'removed'}")
            listeners |= item.startswith(_LISTENER_TABLES) and not restart
            continue
        text = f"{key} {before.get(key, '(none)')} → {asked.get(key, '(none)')}"
        if after.get(key) == before.get(key) or _listener_restart_only(key):
            kept.append(text)
            continue
        changes.append(text)
        table, _, rest = key.partition(".")
        if table == "lines":
            line, _, setting = rest.partition(".")
            (reopened if setting in reopening else retuned).add(line)
        listeners |= key.startswith(_LISTENER_TABLES)
    effects = [f"line {name} reopened" for name in sorted(reopened)]
    effects += [f"line {name} retuned in place" for name in sorted(retuned - reopened)]
    if listeners:
        effects.append(
            "listeners changed (rules, allow lists, certificates; open connections checked again)"
        )
    if kept:
        effects.append("needs a restart, kept at its running value: " + "; ".join(kept))
    if not changes and not kept:
        return "no key changed (certificate and key files were read again)"
    return "; ".join(changes + effects)
