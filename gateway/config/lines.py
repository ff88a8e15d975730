"""``[lines.NAME]``: one serial or network line each, and what follows from its settings.

The schema reads most keys; the builders here add what it cannot say: the keys one line
kind takes and another refuses, a network line's address, the automatic timeout, the
slaves' timeouts and names, the read cache, and two lines on one device.
"""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Mapping
from typing import Any

from .. import schema
from ..core.ascii import MAX_ASCII_FRAME
from ..core.framing import is_mbap
from ..core.rtu import MAX_RTU_FRAME
from ..core.timing import transmission_time
from ..schema import Table
from .model import DEFAULT_TLS_PORT, NETWORK_LINE_KINDS, CacheRule, LineConfig
from .reading import Checker, parse_host_port, parse_units, read_scalars

_LINE_KEYS_BY_NAME = schema.keys_of(Table.LINES)


#: Added to the automatic response timeout of a network line: the round trip and the device
#: server's own buffering.
NETWORK_ALLOWANCE_S = 0.1


#: Keys only a ``kind = "tls"`` line takes.
_TLS_LINE_KEYS = tuple(k.name for k in _LINE_KEYS_BY_NAME.values() if k.only == 'kind = "tls"')


#: Line keys with a parser of their own (the rest are read as the schema declares them).
_LINE_SPECIAL = frozenset(
    {
        "kind",
        "device",
        "address",
        "baudrate",
        "data_bits",
        "parity",
        "stop_bits",
        "timeout",
        "units",
        "slave_timeouts",
        "names",
        "cache",
        "max_in_flight",
        *_TLS_LINE_KEYS,
    }
)


#: Line keys stored in a field of another name.
_LINE_FIELDS = {"silence": "silence_setting"}


#: ``LineConfig`` fields whose change makes a reload reopen the line (the schema's
#: ``Reload.REOPENS``; ``address`` shows in ``device``).
LINE_PORT_SETTINGS = tuple(
    "device" if k.name == "address" else _LINE_FIELDS.get(k.name, k.name)
    for k in _LINE_KEYS_BY_NAME.values()
    if k.reload is schema.Reload.REOPENS
)


def build_line(check: Checker, name: str, raw: Mapping[str, Any]) -> LineConfig | None:
    prefix = f"lines.{name}."
    if not isinstance(raw, dict):
        check.fail(f"lines.{name}", "must be a table ([lines.NAME]) with at least a device")
        return None
    table = check.entry(Table.LINES, raw, prefix)
    kind, device, host, port = _line_kind(check, table, prefix)
    form = serial_format(check, Table.LINES, table, prefix, kind == "ascii")
    units: tuple[int, ...] = ()
    if "units" in table:
        try:
            units = tuple(parse_units(table["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    scalars = read_scalars(check, Table.LINES, table, prefix, _LINE_SPECIAL)
    return LineConfig(
        name=name,
        device=device,
        kind=kind,
        host=host,
        port=port,
        units=units,
        timeout=_line_timeout(check, table, prefix, kind, form),
        learn_timeouts=table.get("timeout", "auto") == "auto",
        slave_timeouts=_slave_timeouts(check, table, prefix),
        names=_slave_names(check, table, prefix),
        cache=_cache_rules(check, table, prefix),
        max_in_flight=_max_in_flight(check, table, prefix, kind),
        **form,
        **{_LINE_FIELDS.get(key, key): value for key, value in scalars.items()},
        **_tls_line(check, table, prefix, kind, host),
    )


def _line_kind(check: Checker, table: Mapping[str, Any], prefix: str) -> tuple[str, str, str, int]:
    """The line's kind, its device (or shown address), and a network line's host and port."""
    kind: str = check.read(_LINE_KEYS_BY_NAME["kind"], table, prefix)
    host, port = "", 0
    device = table.get("device")
    if kind in NETWORK_LINE_KINDS:
        host, port, device = _network_address(check, table, prefix, kind)
    elif "address" in table:
        check.fail(
            f"{prefix}address",
            'only a network line takes it (kind = "rtu-over-tcp", '
            f'"tcp" or "tls"); a {kind} line names its serial port with device',
        )
    if kind not in NETWORK_LINE_KINDS and (not isinstance(device, str) or not device):
        check.fail(
            f"{prefix}device",
            'missing; set the serial device or URL, like "/dev/ttyUSB0" '
            'or "socket://10.0.0.5:4001"',
        )
    return kind, device if isinstance(device, str) else "", host, port


def _network_address(
    check: Checker, table: Mapping[str, Any], prefix: str, kind: str
) -> tuple[str, int, str]:
    """``address = "HOST:PORT"`` of a network line: host, port and the text shown as its device."""
    if "device" in table:
        check.fail(
            f"{prefix}device",
            f'a {kind} line is reached at address = "HOST:PORT", '
            "not a device; rename the key to address",
        )
    value = table.get("address")
    if kind == "tls" and isinstance(value, str) and value and not _has_port(value):
        value = f"{value}:{DEFAULT_TLS_PORT}"  # Modbus/TCP Security's own port
    if not isinstance(value, str) or not value:
        check.fail(
            f"{prefix}address",
            f'missing; a {kind} line needs the device server\'s address, like "10.0.0.5:4001"',
        )
        return "", 0, ""
    try:
        host, port = parse_host_port(value)
    except ValueError as error:
        check.fail(f"{prefix}address", str(error))
        return "", 0, ""
    if port == 0 or host in ("0.0.0.0", "::"):
        check.fail(
            f"{prefix}address",
            f"{value!r} is not a place to connect to; "
            'write the device server\'s address, like "10.0.0.5:4001"',
        )
        return "", 0, ""
    shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    return host, port, shown


def _has_port(address: str) -> bool:
    """True when ``address`` ends in ``:PORT`` (``[v6]`` alone, or a bare host, has none)."""
    _, sep, tail = address.rpartition(":")
    return bool(sep) and tail.isdigit() and not address.endswith("]")


def serial_format(
    check: Checker, where: Table, table: Mapping[str, Any], prefix: str, ascii_line: bool
) -> dict[str, Any]:
    """Baud rate, data bits, parity and stop bits (7E1 by default on an ASCII line:
    Modbus over Serial Line 2.5.2.1)."""
    keys = schema.keys_of(where)
    return {
        "baudrate": check.read(keys["baudrate"], table, prefix),
        "data_bits": check.read(keys["data_bits"], table, prefix, 7 if ascii_line else 8),
        "parity": check.read(keys["parity"], table, prefix, "E" if ascii_line else "N"),
        "stop_bits": check.read(keys["stop_bits"], table, prefix),
    }


def _line_timeout(
    check: Checker, table: Mapping[str, Any], prefix: str, kind: str, form: Mapping[str, Any]
) -> float:
    """``timeout``: the seconds written, or "auto" (see ``auto_timeout``)."""
    longest = MAX_ASCII_FRAME if kind == "ascii" else MAX_RTU_FRAME
    timeout = auto_timeout(
        form["baudrate"], form["data_bits"], form["parity"], form["stop_bits"], longest
    )
    if kind in NETWORK_LINE_KINDS:
        timeout = round(timeout + NETWORK_ALLOWANCE_S, 3)
    if table.get("timeout", "auto") != "auto":
        timeout = check.read(_LINE_KEYS_BY_NAME["timeout"], table, prefix, timeout)
    return timeout


#: Time a slave is given to start its answer, on top of the longest answer's transmission.
SLAVE_TURNAROUND_S = 0.1


def auto_timeout(
    baudrate: int,
    data_bits: int = 8,
    parity: str = "N",
    stop_bits: float = 1,
    longest_frame: int = MAX_RTU_FRAME,
) -> float:
    """The default response timeout (``timeout = "auto"``) of a line with these settings.

    The timeout runs from the end of the request to the end of the answer, so it must hold
    the longest answer's transmission (256 characters) plus the slave's turnaround (0.1 s):
    0.367 s at 9600 8N1, 0.393 s at 9600 8E1. Two attempts (``retries = 1``) then end before
    a master's common 1 s timeout at 9600 baud and faster, so the master gets the gateway's
    0x0B rather than a timeout of its own; slower lines get proportionally longer. ASCII
    lines hold 513 characters instead: 0.634 s at 9600 7E1.
    """
    longest = transmission_time(longest_frame, baudrate, data_bits, parity, stop_bits)
    return round(SLAVE_TURNAROUND_S + longest, 3)


def _usable_server_name(name: str) -> bool:
    """True for a name TLS can check: an IP address, or a host name IDNA can encode."""
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        pass
    if any(character.isspace() or not character.isprintable() for character in name):
        return False
    try:
        name.encode("idna")
    except UnicodeError:
        return False
    return True


def _tls_line(
    check: Checker, table: Mapping[str, Any], prefix: str, kind: str, host: str
) -> dict[str, Any]:
    """The TLS keys of a ``kind = "tls"`` line (refused on any other kind)."""
    if kind != "tls":
        for key in _TLS_LINE_KEYS:
            if key in table:
                check.fail(
                    f"{prefix}{key}",
                    f'only a kind = "tls" line takes it; remove it from this {kind} line',
                )
        return {}
    what = {
        "cert": "the gateway's client certificate chain (PEM, leaf first)",
        "key": "the private key of that certificate (PEM, unencrypted)",
        "ca": "the CA certificates the slave's certificate must chain to (PEM)",
    }
    files: dict[str, str | None] = {}
    for key, description in what.items():
        value = table.get(key)
        if not isinstance(value, str) or not value:
            fix = "write a file path as a string" if key in table else "missing"
            check.fail(
                f"{prefix}{key}",
                f"{fix}; a tls line needs {description} (or --modbus-tls-{key} FILE)",
            )
            value = None
        files[key] = value
    server_name = table.get("server_name", host)
    if not isinstance(server_name, str) or not server_name:
        check.fail(
            f"{prefix}server_name",
            "write the name the slave's certificate carries, "
            'like "plc-7.plant.example" (default: the address\'s host)',
        )
        server_name = host
    elif not _usable_server_name(server_name):
        check.fail(
            f"{prefix}server_name",
            f"{server_name!r} is not a host name or address; "
            "write the name the slave's certificate carries, like "
            '"plc-7.plant.example"',
        )
        server_name = host
    return {
        **files,
        "server_name": server_name,
        "check_server_name": check.read(_LINE_KEYS_BY_NAME["check_server_name"], table, prefix),
        "tls_handshake_timeout": check.read(
            _LINE_KEYS_BY_NAME["tls_handshake_timeout"], table, prefix
        ),
    }


def _max_in_flight(check: Checker, table: Mapping[str, Any], prefix: str, kind: str) -> int:
    """Requests outstanding at once: only where answers carry their request's number (MBAP)."""
    if "max_in_flight" not in table:
        return 1
    if not is_mbap(kind):
        check.fail(
            f"{prefix}max_in_flight",
            f'only a Modbus TCP line (kind = "tcp" or "tls") takes it: a {kind} line\'s '
            "answers carry no transaction id, so it has one request on the wire; remove the key",
        )
        return 1
    return int(check.read(_LINE_KEYS_BY_NAME["max_in_flight"], table, prefix))


def _slave_timeouts(check: Checker, table: Mapping[str, Any], prefix: str) -> dict[int, float]:
    raw = table.get("slave_timeouts", {})
    key = f"{prefix}slave_timeouts"
    if not isinstance(raw, dict):
        check.fail(key, 'write a table of slave = seconds, like { "5" = 0.3 }')
        return {}
    timeouts: dict[int, float] = {}
    for slave_text in raw:
        if not slave_text.isdigit() or not 1 <= int(slave_text) <= 247:
            check.fail(f"{key}.{slave_text}", "the key must be a slave address 1..247, quoted")
            continue
        low, high = _LINE_KEYS_BY_NAME["timeout"].float_range()
        timeouts[int(slave_text)] = check.number(raw, slave_text, f"{key}.", 1.0, low, high)
    return timeouts


#: The longest slave name ``names`` takes (a status page cell, not a document).
MAX_NAME_LENGTH = 64


def _slave_names(check: Checker, table: Mapping[str, Any], prefix: str) -> dict[int, str]:
    """``names = { "1" = "plc" }``: keyed by slave address, as ``slave_timeouts`` is."""
    raw = table.get("names", {})
    key = f"{prefix}names"
    if not isinstance(raw, dict):
        check.fail(key, 'write a table of slave = name, like { "1" = "plc" }')
        return {}
    names: dict[int, str] = {}
    for slave_text, name in raw.items():
        if not slave_text.isdigit() or not 1 <= int(slave_text) <= 247:
            check.fail(f"{key}.{slave_text}", "the key must be a slave address 1..247, quoted")
        elif not isinstance(name, str) or not name.strip() or len(name) > MAX_NAME_LENGTH:
            check.fail(
                f"{key}.{slave_text}",
                f"{name!r} is not a name of 1..{MAX_NAME_LENGTH} characters in quotes",
            )
        else:
            names[int(slave_text)] = name.strip()
    return names


_CACHE_FUNCTIONS = (1, 2, 3, 4)


def _cache_rules(check: Checker, table: Mapping[str, Any], prefix: str) -> tuple[CacheRule, ...]:
    raw = table.get("cache", [])
    key = f"{prefix}cache"
    if not isinstance(raw, list):
        check.fail(
            key, "write [[lines.NAME.cache]] tables with unit, function, start, count, max_age"
        )
        return ()
    rules: list[CacheRule] = []
    for index, entry in enumerate(raw):
        entry_key = f"{key}[{index}]."
        if not isinstance(entry, dict):
            check.fail(
                f"{key}[{index}]", "must be a table with unit, function, start, count, max_age"
            )
            continue
        entry = check.entry(Table.CACHE, entry, entry_key)
        values = read_scalars(check, Table.CACHE, entry, entry_key, ())
        if values["function"] in _CACHE_FUNCTIONS:
            rules.append(CacheRule(**values))
    return tuple(rules)


def device_identity(device: str) -> str:
    """What makes two ``device`` values the same port: the resolved path (by-id symlinks)."""
    return device if "://" in device else os.path.realpath(device)


def check_shared_devices(check: Checker, lines: tuple[LineConfig, ...]) -> None:
    """Two lines on one device would interleave their frames on the wire: an error."""
    owners: dict[str, str] = {}
    for line in lines:
        if not line.device:
            continue
        identity = line.device if line.is_url else device_identity(line.device)
        owner = owners.setdefault(identity, line.name)
        if owner != line.name:
            check.fail(
                f"lines.{line.name}.device",
                f"{line.device!r} is the device of line {owner!r} too; one serial device "
                f"serves one line: merge the two lines' units into lines.{owner}",
            )
