"""What runs beside the lines and listeners: the HTTP endpoint (``[metrics]``), the log
(``[logging]``), the audit log (``[audit]``) and the redundancy pair (``[redundancy]``).
"""

from __future__ import annotations

import ipaddress
import string
from collections.abc import Mapping
from typing import Any

from .. import schema
from ..core.redundancy import HEARING_DELAY_S
from ..schema import Table
from .model import AuditConfig, LoggingConfig, MetricsConfig, RedundancyConfig
from .reading import Checker, read_scalars

#: Where ``metrics.listen = "auto"`` binds, on a port the OS chooses.
AUTO_METRICS_HOST = "127.0.0.1"


#: What a token may hold: it travels unencoded in a header, a cookie and a link.
_TOKEN_CHARACTERS = frozenset(string.ascii_letters + string.digits + "-._~")


#: The ``[metrics]`` keys that hold text: host names, tokens, file paths.
_METRICS_TEXT = ("allowed_hosts", "status_token", "trace_token", "tls_cert", "tls_key", "tls_ca")


def build_metrics(check: Checker, raw: Mapping[str, Any]) -> MetricsConfig:
    prefix = "metrics."
    table = check.entry(Table.METRICS, check.table(raw, "metrics"), prefix)
    values = read_scalars(check, Table.METRICS, table, prefix, ("listen", *_METRICS_TEXT))
    values.update(_metrics_text(check, table, prefix))
    if str(table.get("listen", "")).lower() == "auto":  # a free port the OS picks, logged
        return MetricsConfig(True, AUTO_METRICS_HOST, 0, **values)
    address = check.read(schema.key(Table.METRICS, "listen"), table, prefix)
    if address is None:  # "off"
        return MetricsConfig(False, **values)
    return MetricsConfig(True, address[0], address[1], **values)


def _metrics_text(check: Checker, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """The endpoint's host names, tokens and TLS files, checked."""
    values: dict[str, Any] = {}
    hosts = table.get("allowed_hosts", [])
    if not isinstance(hosts, list) or not all(isinstance(h, str) and h for h in hosts):
        check.fail(f"{prefix}allowed_hosts", 'write a list of host names, like ["gw.example"]')
        hosts = []
    values["allowed_hosts"] = tuple(h.lower().rstrip(".") for h in hosts)
    for name in _METRICS_TEXT[1:]:
        value = table.get(name)
        if value is not None and (not isinstance(value, str) or not value):
            check.fail(f"{prefix}{name}", "write a non-empty string")
            value = None
        values[name] = value
    for name in ("status_token", "trace_token"):
        token = values[name]
        if token is not None and not all(c in _TOKEN_CHARACTERS for c in token):
            check.fail(
                f"{prefix}{name}",
                "use letters, digits and - . _ ~ only (it travels "
                "in a header, a cookie and a link unencoded)",
            )
        elif token is not None and len(token) < 16:
            check.fail(
                f"{prefix}{name}",
                "too short to resist guessing; use 16 characters "
                "or more, like the output of: openssl rand -hex 16",
            )
    if (values["tls_cert"] is None) != (values["tls_key"] is None):
        check.fail(f"{prefix}tls_cert", "HTTPS needs both tls_cert and tls_key")
    if values["tls_ca"] is not None and values["tls_cert"] is None:
        check.fail(f"{prefix}tls_ca", "client certificates need HTTPS: set tls_cert and tls_key")
    return values


#: Names that always mean this machine (a rebinding page cannot send them as its Host).
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})


def is_loopback(name: str) -> bool:
    """True for a loopback name or address (``127.0.0.0/8``, ``::1``, ``*.localhost``)."""
    if name in LOOPBACK_NAMES or name.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def build_logging(check: Checker, raw: Mapping[str, Any]) -> LoggingConfig:
    prefix = "logging."
    table = check.entry(Table.LOGGING, check.table(raw, "logging"), prefix)
    return LoggingConfig(**read_scalars(check, Table.LOGGING, table, prefix, ()))


def build_audit(check: Checker, raw: Mapping[str, Any]) -> AuditConfig:
    prefix = "audit."
    table = check.entry(Table.AUDIT, check.table(raw, "audit"), prefix)
    path = table.get("path")
    if path is not None and (not isinstance(path, str) or not path):
        check.fail(f"{prefix}path", 'write a file path, as a string ("-": standard error)')
        path = None
    return AuditConfig(path)


def build_redundancy(check: Checker, raw: Mapping[str, Any]) -> RedundancyConfig:
    prefix = "redundancy."
    table = check.entry(Table.REDUNDANCY, check.table(raw, "redundancy"), prefix)
    values = read_scalars(
        check, Table.REDUNDANCY, table, prefix, ("keepalive", "peer", "peer_modbus")
    )
    for name in ("peer", "peer_modbus"):
        if name in table:
            key = schema.key(Table.REDUNDANCY, name)
            values[name] = check.read(key, table, prefix, default="127.0.0.1:0")
    keepalive = _keepalive(check, table.get("keepalive", "auto"), prefix)
    config = RedundancyConfig(**values, keepalive=keepalive)
    if config.peer is not None and config.peer_modbus is None:
        check.fail(
            f"{prefix}peer_modbus",
            "set the peer's Modbus TCP listener, HOST:PORT, "
            "where a standby forwards its masters' requests",
        )
    if config.peer is None and config.peer_modbus is not None:
        check.fail(
            f"{prefix}peer",
            "set the peer's HTTP endpoint, HOST:PORT, or remove peer_modbus: a pair needs both",
        )
    if config.takeover_after <= config.lease + HEARING_DELAY_S:
        check.fail(
            f"{prefix}takeover_after",
            f"must be longer than the lease plus "
            f"{HEARING_DELAY_S:g} s ({config.lease + HEARING_DELAY_S:g} s): "
            "the active's frames must reach the standby before its wait ends",
        )
    return config


def _keepalive(check: Checker, value: object, prefix: str) -> tuple[int, int] | None:
    """``"auto"``, ``"off"`` or ``"SLAVE:REGISTER"``."""
    if value == "off":
        return None
    if value == "auto":
        return (0, 0)
    if isinstance(value, str):
        slave, _, register = value.partition(":")
        digits = slave.isdigit() and register.isdigit()
        if digits and 1 <= int(slave) <= 247 and 0 <= int(register) <= 65535:
            return int(slave), int(register)
    check.fail(
        f"{prefix}keepalive",
        'write "auto", "off", or "SLAVE:REGISTER" with a slave '
        'address 1..247 and a holding register 0..65535, like "1:0"',
    )
    return (0, 0)
