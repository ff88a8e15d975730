"""Configuration checks an operator relies on: shared devices, overlaps, typos, warnings."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import (
    GatewayConfig,
    auto_timeout,
    build_config,
    config_warnings,
    format_units,
    parse_units,
)
from gateway.core.timing import t35, transmission_time
from tests.helpers import problems


def test_two_lines_on_one_device_is_an_error() -> None:
    found = problems(
        {
            "lines": {
                "a": {"device": "/dev/ttyUSB0", "units": [1]},
                "b": {"device": "/dev/ttyUSB0", "units": [2]},
            }
        }
    )
    assert found == [
        "lines.b.device: '/dev/ttyUSB0' is the device of line 'a' too; one serial device "
        "serves one line: merge the two lines' units into lines.a"
    ]


def test_a_device_named_through_a_symlink_is_the_same_device(tmp_path: Path) -> None:
    device = tmp_path / "ttyUSB0"
    device.touch()
    alias = tmp_path / "usb-FTDI_FT232R_USB_UART_A10K1ABC-if00-port0"
    alias.symlink_to(device)
    found = problems(
        {
            "lines": {
                "a": {"device": str(device), "units": [1]},
                "b": {"device": str(alias), "units": [2]},
            }
        }
    )
    assert len(found) == 1 and found[0].startswith("lines.b.device: "), found


def test_the_same_serial_server_url_twice_is_an_error() -> None:
    found = problems(
        {
            "lines": {
                "a": {"device": "socket://10.0.0.5:4001", "units": [1]},
                "b": {"device": "socket://10.0.0.5:4001", "units": [2]},
            }
        }
    )
    assert [problem.split(":")[0] for problem in found] == ["lines.b.device"]


def test_overlapping_units_are_one_message_with_ranges() -> None:
    found = problems(
        {
            "lines": {
                "a": {"device": "/dev/ttyUSB0", "units": ["1-100", 120]},
                "b": {"device": "/dev/ttyUSB1", "units": ["1-247"]},
                "c": {"device": "/dev/ttyUSB2", "units": [120]},
            }
        }
    )
    assert found == [
        "lines.b.units: units 1-100, 120 already routed to line 'a'; give each unit one line",
        "lines.c.units: unit 120 already routed to line 'a'; give each unit one line",
    ]


@pytest.mark.parametrize(
    ("table", "key", "suggestion"),
    [
        ("lines", "baudate", "baudrate"),
        ("lines", "timout", "timeout"),
        ("server", "max_conections", "max_connections"),
        ("metrics", "listn", "listen"),
    ],
)
def test_an_unknown_key_gets_a_did_you_mean(table: str, key: str, suggestion: str) -> None:
    raw: dict[str, Any] = {"lines": {"a": {"device": "/dev/ttyUSB0", "units": [1]}}}
    if table == "lines":
        raw["lines"]["a"][key] = 1
        where = f"lines.a.{key}"
    else:
        raw[table] = {key: 1}
        where = f"{table}.{key}"
    assert problems(raw) == [f"{where}: unknown key; did you mean {suggestion!r}?"]


def test_an_unknown_key_like_nothing_lists_the_known_ones() -> None:
    found = problems({"lines": {"a": {"device": "/dev/ttyUSB0", "units": [1], "colour": 1}}})
    assert len(found) == 1
    assert found[0].startswith("lines.a.colour: unknown key; known keys here are: ")
    assert "baudrate" in found[0]


def config(raw: dict[str, Any]) -> GatewayConfig:
    return build_config(raw, "plant.toml")


def test_a_clean_configuration_has_no_warnings(tmp_path: Path) -> None:
    device = tmp_path / "ttyUSB0"
    device.touch()
    assert config_warnings(config({"lines": {"a": {"device": str(device), "units": [1]}}})) == []


def test_a_missing_device_is_a_warning_not_an_error() -> None:
    missing = "/dev/serial/by-id/usb-not-plugged-in"
    assert not os.path.exists(missing)
    warnings = config_warnings(config({"lines": {"a": {"device": missing, "units": [1]}}}))
    assert warnings == [
        f"lines.a.device: {missing} does not exist (yet); the gateway retries opening it, "
        "check the path (ls /dev/serial/by-id/)"
    ]


def test_a_url_is_not_looked_for_on_disk() -> None:
    raw = {"lines": {"a": {"device": "socket://10.0.0.5:4001", "units": [1]}}}
    assert config_warnings(config(raw)) == []


def test_a_line_without_units_is_a_warning_unless_a_route_uses_it() -> None:
    raw: dict[str, Any] = {
        "lines": {"a": {"device": "/dev/null", "units": [1]}, "b": {"device": "/dev/zero"}}
    }
    assert config_warnings(config(raw)) == [
        "lines.b.units: no unit is routed to this line; add units = [...] or a [[routes]] "
        'entry with line = "b"'
    ]
    raw["routes"] = [{"unit": 100, "line": "b", "slave": 1}]
    assert config_warnings(config(raw)) == []


@pytest.mark.parametrize(
    ("listen", "metrics", "clash"),
    [
        ("0.0.0.0:9502", "127.0.0.1:9502", True),
        ("127.0.0.1:5020", "127.0.0.1:5020", True),
        ("127.0.0.1:5020", "0.0.0.0:5020", True),
        ("127.0.0.1:5020", "127.0.0.2:5020", False),
        ("0.0.0.0:502", "0.0.0.0:9502", False),
        ("127.0.0.1:0", "127.0.0.1:0", False),
        ("0.0.0.0:9502", "off", False),
    ],
)
def test_modbus_and_metrics_on_one_port_is_a_warning(
    listen: str, metrics: str, clash: bool
) -> None:
    raw = {
        "server": {"listen": listen},
        "metrics": {"listen": metrics},
        "lines": {"a": {"device": "/dev/null", "units": [1]}},
    }
    warnings = config_warnings(config(raw))
    clashes = [w for w in warnings if w.startswith("metrics.listen: port ")]
    assert len(clashes) == clash, warnings


def test_format_units_examples() -> None:
    assert format_units([]) == ""
    assert format_units([5]) == "5"
    assert format_units([3, 1, 2, 7, 9, 10, 10]) == "1-3, 7, 9-10"


@given(st.sets(st.integers(1, 247)))
def test_format_units_round_trips_through_parse_units(units: set[int]) -> None:
    text = format_units(units)
    parsed = parse_units(text.split(", ")) if text else []
    assert parsed == sorted(units)
    assert len(text.split(", ")) <= len(units) or not units


# ------------------------------------------------------------------------ the default timeout


@pytest.mark.parametrize(
    ("baudrate", "parity", "stop_bits", "expected"),
    [
        (9600, "N", 1, 0.367),  # 256 x 10 bits / 9600 = 0.267 s, + 0.1 s
        (9600, "E", 1, 0.393),
        (19200, "E", 1, 0.247),
        (115200, "N", 1, 0.122),
        (1200, "N", 1, 2.233),  # a slow line waits as long as its longest answer needs
    ],
)
def test_auto_timeout_is_the_longest_answer_plus_the_turnaround(
    baudrate: int, parity: str, stop_bits: float, expected: float
) -> None:
    assert auto_timeout(baudrate, 8, parity, stop_bits) == expected
    line = {"device": "/dev/null", "units": [1], "baudrate": baudrate, "parity": parity,
            "stop_bits": stop_bits}  # fmt: skip
    for table in (line, {**line, "timeout": "auto"}):
        assert config({"lines": {"a": table}}).lines[0].timeout == expected


def test_an_explicit_timeout_wins_and_a_bad_one_is_named() -> None:
    raw: dict[str, Any] = {"lines": {"a": {"device": "/dev/null", "units": [1], "timeout": 1.5}}}
    assert config(raw).lines[0].timeout == 1.5
    raw["lines"]["a"]["timeout"] = "slow"
    assert problems(raw) == ["lines.a.timeout: 'slow' is not a number of seconds; write e.g. 0.367"]


@given(
    baudrate=st.integers(9600, 4_000_000),
    data_bits=st.sampled_from([7, 8]),
    parity=st.sampled_from(["N", "E", "O"]),
    stop_bits=st.sampled_from([1.0, 1.5, 2.0]),
)
def test_with_defaults_a_silent_slave_is_answered_well_within_a_second(
    baudrate: int, data_bits: int, parity: str, stop_bits: float
) -> None:
    """Two attempts (retries = 1) of an 8-byte request, each followed by the timeout, plus
    the frame gap between them: under 0.9 s at 9600 baud and faster, whatever the format."""
    timeout = auto_timeout(baudrate, data_bits, parity, stop_bits)
    request = transmission_time(8, baudrate, data_bits, parity, stop_bits)
    gap = t35(baudrate, data_bits, parity, stop_bits)
    assert 2 * (request + timeout) + gap < 0.9
