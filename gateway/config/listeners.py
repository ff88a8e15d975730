"""``[server]`` and ``[[listeners]]``: where masters reach the gateway.

``[server] listen`` is the shorthand tcp listener, present when written or when no other
network listener is; every listener is a ``ListenerConfig``, a ``serial-slave`` one with
the serial line it answers on.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from .. import schema
from ..core.policy import Rule
from ..schema import Key, Table
from .lines import device_identity, serial_format
from .model import DEFAULT_TLS_PORT, LineConfig, ListenerConfig, ServerConfig
from .reading import Checker, networks, parse_host_port, parse_units, policy_name, read_scalars

DEFAULT_LISTEN = str(schema.key(Table.SERVER, "listen").default)


def _function_codes(
    check: Checker, table: Mapping[str, Any], key: Key, prefix: str
) -> frozenset[int]:
    """A list of function codes (``refuse_functions``)."""
    raw = table.get(key.name, key.default)
    low, high = key.int_range()
    if not isinstance(raw, list) or not all(
        isinstance(code, int) and not isinstance(code, bool) and low <= code <= high for code in raw
    ):
        check.fail(
            f"{prefix}{key.name}", f"write a list of function codes {low}..{high}, like [8, 17]"
        )
        return frozenset()
    return frozenset(raw)


def build_server(check: Checker, raw: Mapping[str, Any]) -> ServerConfig:
    prefix = "server."
    table = check.entry(Table.SERVER, check.table(raw, "server"), prefix)
    keys = schema.keys_of(Table.SERVER)
    listen = check.read(keys["listen"], table, prefix) or parse_host_port(DEFAULT_LISTEN)
    return ServerConfig(
        host=listen[0],
        port=listen[1],
        refuse_functions=_function_codes(check, table, keys["refuse_functions"], prefix),
        allow=networks(check, table, "allow", prefix),
        policy=policy_name(check, table, prefix),
        **read_scalars(
            check, Table.SERVER, table, prefix, ("listen", "refuse_functions", "allow", "policy")
        ),
    )


_LISTENER_TABLE = schema.keys_of(Table.LISTENERS)


#: Keys of a ``serial-slave`` listener only: its serial line, and the units it answers for.
_SERIAL_SLAVE_KEYS = frozenset(
    k.name for k in _LISTENER_TABLE.values() if k.only.startswith('protocol = "serial-slave"')
)


#: What a tls listener's files hold, for the message when one is missing.
_LISTENER_FILES = {
    "cert": "the server's certificate chain (PEM)",
    "key": "the server's private key (PEM)",
    "ca": "the CA certificates client certificates must chain to (PEM)",
}


def build_listeners(
    check: Checker,
    raw: Mapping[str, Any],
    server: ServerConfig,
    policies: Mapping[str, tuple[Rule, ...]],
) -> tuple[ListenerConfig, ...]:
    """``[server] listen`` (the shorthand tcp listener) and every ``[[listeners]]`` entry."""
    entries = raw.get("listeners", [])
    if not isinstance(entries, list):
        check.fail("listeners", "write listeners as [[listeners]] tables")
        entries = []
    listeners = _shorthand_listener(check, raw, server, entries)
    for index, entry in enumerate(entries):
        listener = _listener(check, entry, index, server)
        if listener is not None:
            listeners.append(listener)
    _check_listeners(check, listeners, policies)
    return tuple(listeners)


def _shorthand_listener(
    check: Checker, raw: Mapping[str, Any], server: ServerConfig, entries: list[Any]
) -> list[ListenerConfig]:
    """The ``[server] listen`` listener: when written (or ``--listen`` given), or when no
    other network listener is configured, as before listeners existed (a ``serial-slave``
    listener does not replace it)."""
    networked = [
        e for e in entries if not (isinstance(e, dict) and e.get("protocol") == "serial-slave")
    ]
    if "listen" not in check.table(raw, "server") and networked:
        return []
    return [
        ListenerConfig(
            name="tcp",
            protocol="tcp",
            host=server.host,
            port=server.port,
            read_only=server.read_only,
            policy=server.policy,
        )
    ]


def _listener(check: Checker, raw: Any, index: int, server: ServerConfig) -> ListenerConfig | None:
    """One ``[[listeners]]`` entry (``None`` when it is not even a table)."""
    key = f"listeners[{index}]"
    if not isinstance(raw, dict):
        check.fail(key, "must be a table with name, protocol and listen")
        return None
    prefix = f"{key}."
    entry = check.entry(Table.LISTENERS, raw, prefix)
    protocol: str = check.read(_LISTENER_TABLE["protocol"], entry, prefix)
    name = entry.get("name", protocol)
    if not isinstance(name, str) or not name.replace("-", "_").isidentifier():
        check.fail(f"{prefix}name", f"{name!r}: write a short name of letters, digits, - or _")
        name = f"listener{index}"
    common: dict[str, Any] = {
        "name": name,
        "protocol": protocol,
        "key_prefix": prefix,
        "read_only": check.read(_LISTENER_TABLE["read_only"], entry, prefix) or server.read_only,
        "policy": policy_name(check, entry, prefix),
    }
    if protocol == "serial-slave":
        serial, units = _serial_slave_line(check, entry, prefix, name)
        for other in ("cert", "key", "ca", "crl", "allow"):
            if other in entry:
                check.fail(
                    f"{prefix}{other}", "a serial-slave listener has no network peers: remove it"
                )
        return ListenerConfig(host="", port=0, serial=serial, units=units, **common)
    for serial_key in sorted(_SERIAL_SLAVE_KEYS & set(entry)):
        check.fail(f"{prefix}{serial_key}", 'only a protocol = "serial-slave" listener takes it')
    default_port = DEFAULT_TLS_PORT if protocol == "tls" else 502
    address = check.address(entry, "listen", prefix, f"0.0.0.0:{default_port}")
    if address is None:
        check.fail(f"{prefix}listen", 'a listener needs an address; write it like "0.0.0.0:802"')
        address = ("0.0.0.0", default_port)
    return ListenerConfig(
        host=address[0],
        port=address[1],
        allow=networks(check, entry, "allow", prefix),
        **_listener_files(check, entry, prefix, protocol),
        **_listener_tls(check, entry, prefix, protocol),
        **common,
    )


def _serial_slave_line(
    check: Checker, entry: Mapping[str, Any], prefix: str, name: str
) -> tuple[LineConfig, tuple[int, ...]]:
    """The serial line of a ``serial-slave`` listener, and the units it answers for."""
    device = entry.get("device")
    if not isinstance(device, str) or not device:
        check.fail(
            f"{prefix}device",
            "missing; a serial-slave listener answers on a serial "
            'device, like "/dev/ttyUSB1" (or --serial-slave DEVICE)',
        )
        device = ""
    if "listen" in entry:
        check.fail(f"{prefix}listen", "a serial-slave listener has a device, not an address")
    units: tuple[int, ...] = ()
    if "units" in entry:
        try:
            units = tuple(parse_units(entry["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    framing: str = check.read(_LISTENER_TABLE["framing"], entry, prefix)
    ascii_line = framing == "ascii"
    line = LineConfig(
        name=f"listener {name}",
        device=device,
        kind=framing,
        inter_char_timeout=check.read(_LISTENER_TABLE["inter_char_timeout"], entry, prefix),
        echo=check.read(_LISTENER_TABLE["echo"], entry, prefix),
        **serial_format(check, Table.LISTENERS, entry, prefix, ascii_line),
    )
    if "inter_char_timeout" in entry and not ascii_line:
        check.fail(
            f"{prefix}inter_char_timeout",
            'only an ASCII line has one (framing = "ascii"); an RTU frame ends on t3.5 of silence',
        )
    return line, units


def _listener_files(
    check: Checker, entry: Mapping[str, Any], prefix: str, protocol: str
) -> dict[str, Any]:
    """``cert``, ``key`` and ``ca``: required on a tls listener, refused on any other."""
    files: dict[str, str | None] = {}
    for file_key, what in _LISTENER_FILES.items():
        value = entry.get(file_key)
        if value is not None and (not isinstance(value, str) or not value):
            check.fail(f"{prefix}{file_key}", "write a file path as a string")
            value = None
        if protocol == "tls" and value is None:
            check.fail(
                f"{prefix}{file_key}",
                f"missing; a tls listener needs {what} (or --tls-{file_key} FILE)",
            )
        if protocol != "tls" and value is not None:
            check.fail(f"{prefix}{file_key}", 'only a protocol = "tls" listener takes it')
        files[file_key] = value
    return files


def _listener_tls(
    check: Checker, entry: Mapping[str, Any], prefix: str, protocol: str
) -> dict[str, Any]:
    """``crl``, ``forward_secrecy_only``, ``session_resumption``: a tls listener's options."""
    names = ("crl", "forward_secrecy_only", "session_resumption")
    if protocol != "tls":
        for name in names:
            if name in entry:
                check.fail(f"{prefix}{name}", 'only a protocol = "tls" listener takes it')
        return {}
    crl = entry.get("crl")
    if crl is not None and (not isinstance(crl, str) or not crl):
        check.fail(f"{prefix}crl", "write a file path as a string")
        crl = None
    return {
        "crl": crl,
        **{name: check.read(_LISTENER_TABLE[name], entry, prefix) for name in names[1:]},
    }


def _check_listeners(
    check: Checker, listeners: list[ListenerConfig], policies: Mapping[str, tuple[Rule, ...]]
) -> None:
    """Names unique, policies defined, one listener per address."""
    seen: dict[str, ListenerConfig] = {}
    for listener in listeners:
        if listener.name in seen:
            check.fail(
                f"{listener.key_prefix}name",
                f"{listener.name!r} is used by another listener; give each listener its own name",
            )
        seen[listener.name] = listener
        if listener.policy is not None and listener.policy not in policies:
            known = ", ".join(sorted(policies)) or "(none defined)"
            check.fail(
                f"{listener.key_prefix}policy",
                f"{listener.policy!r} is not a [policies.NAME] table; policies are: {known}",
            )
    addresses = [(lst.host, lst.port) for lst in listeners if lst.port != 0]
    for address in set(addresses):
        if addresses.count(address) > 1:
            check.fail(
                "listeners", f"two listeners on {address[0]}:{address[1]}; give each its own port"
            )


def check_serial_slave_devices(
    check: Checker, lines: tuple[LineConfig, ...], listeners: Iterable[ListenerConfig]
) -> None:
    """A serial-slave listener's device is its own: not a line's, not another listener's."""
    owners = {
        (line.device if line.is_url else device_identity(line.device)): f"line {line.name!r}"
        for line in lines
        if line.device
    }
    for listener in listeners:
        serial = listener.serial
        if serial is None or not serial.device:
            continue
        identity = serial.device if serial.is_url else device_identity(serial.device)
        owner = owners.setdefault(identity, f"listener {listener.name!r}")
        if owner != f"listener {listener.name!r}":
            check.fail(
                f"{listener.key_prefix}device",
                f"{serial.device!r} is the device of {owner} too; a serial-slave listener "
                "needs a serial line of its own",
            )
