"""The whole configuration: every table built, the cross-checks between tables made, and
every problem raised at once.

Theory of operation: ``read_config_file`` parses the file, the CLI merges its flags into
the raw tables, and ``build_config`` validates everything at once, so that one
``ConfigError`` lists every fault with its file, key and fix instead of stopping at the
first. Which keys each table takes, their defaults, ranges, choices and former names come
from the schema (``gateway.schema``); the builders add what the schema cannot say (a key
one line kind takes, cross-checks). Nothing here opens a port.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from .. import schema
from .lines import build_line, check_shared_devices
from .listeners import build_listeners, build_server, check_serial_slave_devices
from .model import GatewayConfig
from .policies import build_policies
from .polling import build_polling, build_polls
from .reading import Checker, ConfigError, read_config_file
from .routes import build_routes
from .services import build_audit, build_logging, build_metrics, build_redundancy


def build_config(raw: Mapping[str, Any], source: str = "<command line>") -> GatewayConfig:
    """Validate raw tables into a ``GatewayConfig``; raise ``ConfigError`` listing every fault."""
    check = Checker()
    check.unknown_keys(raw, set(schema.TOP_LEVEL), "")
    server = build_server(check, raw)
    metrics = build_metrics(check, raw)
    log = build_logging(check, raw)
    audit = build_audit(check, raw)
    redundancy = build_redundancy(check, raw)
    if redundancy.paired and not metrics.enabled:
        check.fail(
            "metrics.listen",
            "a redundancy pair polls each other's HTTP endpoint "
            "(GET /role): set it to an address the peer reaches, not off",
        )
    lines_table = check.table(raw, "lines")
    lines = tuple(
        line
        for name, table in lines_table.items()
        if (line := build_line(check, name, table)) is not None
    )
    if not lines:
        check.fail(
            "lines",
            'no serial line configured; add [lines.a] with device = "/dev/ttyUSB0" '
            "(or run with --serial DEVICE, or --demo)",
        )
    routes = build_routes(check, raw, lines)
    polling = build_polling(check, raw, routes, lines)
    polls = build_polls(check, raw, routes, polling)
    lines = tuple(
        replace(line, polls=tuple(block for block in polls if block.line == line.name))
        for line in lines
    )
    policies = build_policies(check, raw)
    listeners = build_listeners(check, raw, server, policies)
    check_shared_devices(check, lines)
    check_serial_slave_devices(check, lines, listeners)
    if check.problems:
        raise ConfigError(source, check.problems)
    return GatewayConfig(
        server,
        metrics,
        log,
        lines,
        routes,
        source,
        listeners,
        policies,
        tuple(check.renamed),
        audit,
        redundancy,
        polls,
        polling,
    )


def load_config(path: str | Path) -> GatewayConfig:
    """Read and validate a configuration file."""
    return build_config(read_config_file(path), str(path))
