"""The reload's log line: each key by its full name, old → new, then what the reload did."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from gateway.config import LINE_PORT_SETTINGS, GatewayConfig, build_config
from gateway.reload_summary import summarize


def _config(**tables: Any) -> GatewayConfig:
    lines = tables.pop("lines", {"a": {"device": "/dev/ttyUSB0", "units": [1], "timeout": 0.5}})
    return build_config({"lines": lines, **tables}, "plant.toml")


def _parts(running: GatewayConfig, wanted: GatewayConfig, applied: GatewayConfig) -> list[str]:
    return summarize(running, wanted, applied, LINE_PORT_SETTINGS).split("; ")


def test_a_retuned_line_names_its_key_with_both_values() -> None:
    running = _config()
    wanted = _config(lines={"a": {"device": "/dev/ttyUSB0", "units": [1], "timeout": 0.7}})
    assert _parts(running, wanted, wanted) == [
        "lines.a.timeout 0.5 → 0.7", "line a retuned in place",
    ]  # fmt: skip


def test_a_port_setting_reopens_and_whole_lines_come_and_go_by_name() -> None:
    running = _config()
    lines = {"a": {"device": "/dev/ttyUSB0", "units": [1], "timeout": 0.5, "baudrate": 19200},
             "b": {"device": "/dev/ttyUSB1", "units": [2]}}  # fmt: skip
    wanted = _config(lines=lines)
    parts = _parts(running, wanted, wanted)
    assert "lines.a.baudrate 9600 → 19200" in parts and "line a reopened" in parts
    assert "lines.b added" in parts and "routes.2 added" in parts
    assert not any(part.startswith("lines.b.") for part in parts)  # named once, as a whole


def test_a_listener_address_is_kept_and_a_policy_change_reaches_the_listeners() -> None:
    running = _config()
    wanted = _config(server={"listen": "0.0.0.0:1502", "read_only": True})
    # What the gateway applies: the address it is bound to stays (needs a restart).
    applied = replace(wanted, server=replace(wanted.server, host=running.server.host,
                                             port=running.server.port))  # fmt: skip
    parts = _parts(running, wanted, applied)
    assert "server.read_only False → True" in parts
    assert any(part.startswith("listeners changed") for part in parts)
    kept = parts.index("needs a restart, kept at its running value: listeners.tcp.port 502 → 1502")
    assert parts[kept + 1 :] == ["server.port 502 → 1502"]  # the rest of the kept list


def test_nothing_changed_says_so() -> None:
    config = _config()
    assert summarize(config, config, config, LINE_PORT_SETTINGS).startswith("no key changed")
