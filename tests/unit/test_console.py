"""The operator console's pieces: slave names, metrics on a free port, answers decoded to
values, per-slave tallies, the utilisation ring and the kernel's UART error counters."""

from __future__ import annotations

import os
import pty

import pytest
from hypothesis import given
from hypothesis import strategies as st
from prometheus_client import generate_latest

from gateway.answer_values import answer_values, exception_name
from gateway.config import ConfigError, build_config
from gateway.core.outcome import Outcome
from gateway.io.http.live import HISTORY_S, LATENCY_WINDOW_S, LatencyWindow, UtilisationHistory
from gateway.io.line.tally import LineTally
from gateway.io.links.uart import UartError, uart_errors
from gateway.metrics import GatewayMetrics


def _line(**keys: object) -> dict[str, object]:
    return {"lines": {"a": {"device": "/dev/ttyUSB0", "units": [1, 2], **keys}}}


def test_names_are_keyed_by_slave_address() -> None:
    config = build_config(_line(names={"1": "plc", "2": " meter "}))
    assert config.lines[0].names == {1: "plc", 2: "meter"}
    assert build_config(_line()).lines[0].names == {}


@pytest.mark.parametrize(
    ("names", "problem"),
    [
        ({"0": "x"}, "lines.a.names.0: the key must be a slave address 1..247"),
        ({"plc": "x"}, "lines.a.names.plc: the key must be a slave address 1..247"),
        ({"1": 5}, "lines.a.names.1: 5 is not a name of 1..64 characters"),
        ({"1": ""}, "lines.a.names.1: '' is not a name"),
        ("plc", "lines.a.names: write a table of slave = name"),
    ],
)
def test_a_bad_name_is_named_with_its_key(names: object, problem: str) -> None:
    with pytest.raises(ConfigError) as raised:
        build_config(_line(names=names))
    assert any(problem in p for p in raised.value.problems), raised.value.problems


def test_metrics_listen_auto_is_a_free_port_on_loopback() -> None:
    metrics = build_config({**_line(), "metrics": {"listen": "auto"}}).metrics
    assert (metrics.enabled, metrics.host, metrics.port) == (True, "127.0.0.1", 0)
    assert not build_config({**_line(), "metrics": {"listen": "off"}}).metrics.enabled


def test_answers_decode_to_values() -> None:
    h = bytes.fromhex
    assert answer_values(h("03 0010 0002"), h("03 04 0113 FF9D")) == {
        "address": 16, "registers": [275, 65437],
    }  # fmt: skip
    assert answer_values(None, h("04 02 002A")) == {"address": None, "registers": [42]}
    assert answer_values(h("01 0000 000A"), h("01 02 05 03")) == {
        "address": 0, "bits": [1, 0, 1, 0, 0, 0, 0, 0, 1, 1],
    }  # fmt: skip
    assert answer_values(h("06 0903 0028"), h("06 0903 0028")) == {
        "address": 2307, "echo": "address=2307 value=0x0028",
    }  # fmt: skip
    assert answer_values(h("03 0000 0001"), h("83 02")) == {
        "exception": 2, "name": "illegal data address",
    }  # fmt: skip
    assert exception_name(0x0B) == "gateway target failed"
    assert exception_name(0x13) == "exception 0x13"
    assert answer_values(None, h("08")) is None
    assert answer_values(None, h("11 03 01 02 FF")) is None  # nothing to number: hex says it


@given(st.binary(max_size=260), st.binary(max_size=260))
def test_decoding_never_fails(request: bytes, reply: bytes) -> None:
    values = answer_values(request or None, reply)
    assert values is None or isinstance(values, dict)


def test_a_tally_counts_requests_exceptions_and_when_last_heard() -> None:
    tally = LineTally()
    tally.count(1, b"\x03\x02\x00\x01", Outcome.OK)
    tally.count(1, b"\x83\x02", Outcome.SLAVE_EXCEPTION)
    tally.count(1, b"\x83\x02", Outcome.SLAVE_EXCEPTION)
    tally.count(2, b"\x83\x0b", Outcome.TARGET_FAILED)  # the gateway's 0x0B: not heard
    one, two = tally.slaves[1], tally.slaves[2]
    assert (one.requests, one.exceptions, one.last_seen is not None) == (3, {2: 2}, True)
    assert (two.requests, two.exceptions, two.last_seen) == (1, {}, None)


def test_the_utilisation_ring_fills_unwatched_intervals_with_their_average() -> None:
    ring = UtilisationHistory()
    assert ring.sample(100.0, 0.0) == ()  # the first look: a baseline
    assert ring.sample(100.0 + HISTORY_S / 2, 1.0) == ()  # not a whole interval yet
    assert ring.sample(100.0 + HISTORY_S, HISTORY_S / 4) == (0.25,)
    # Nobody looked for three intervals: each gets the average busy share over them.
    assert ring.sample(100.0 + 4 * HISTORY_S, HISTORY_S / 4 + 1.5 * HISTORY_S) == (
        0.25, 0.5, 0.5, 0.5,
    )  # fmt: skip
    for step in range(200):
        ring.sample(100.0 + (5 + step) * HISTORY_S, 10.0 * HISTORY_S)
    assert len(ring.sample(1e6, 10.0 * HISTORY_S)) == 60


def test_line_latency_covers_the_recent_window_not_the_time_since_start() -> None:
    """The counts since the snapshot a window ago; the window it covers is said with them."""
    window = LatencyWindow()
    # An hour of fast answers before anybody looked: none of it counts.
    assert window.recent(3600.0, (1000, 0, 0)) == ((0, 0, 0), 0.0)
    assert window.recent(3601.0, (1000, 5, 0)) == ((0, 5, 0), 1.0)  # watching for 1 s
    for step in range(1, 200):  # watched for longer than the window, one read per second
        counts, covered = window.recent(3601.0 + step, (1000, 5 + step, step))
    assert (counts, covered) == ((0, 204, 199), 200.0)  # less than the window: all of it
    counts, covered = window.recent(3601.0 + 400, (1000, 204, 400))
    assert LATENCY_WINDOW_S <= covered <= LATENCY_WINDOW_S + HISTORY_S
    assert counts[0] == 0 and counts[2] >= 300  # the slow answers of the last 5 minutes only
    # The page closed for an hour: a snapshot that old is no base, the window starts again.
    assert window.recent(3601.0 + 4000, (1000, 204, 9999)) == ((0, 0, 0), 0.0)


def test_a_pty_has_no_uart_error_counters() -> None:
    main, side = pty.openpty()
    try:
        assert uart_errors(side) is None
    finally:
        os.close(main)
        os.close(side)


def test_a_serial_driver_gives_its_uart_error_counters() -> None:
    try:
        fd = os.open("/dev/ttyS0", os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as error:
        pytest.skip(f"no 8250 port to ask here: {error}")
    try:
        counts = uart_errors(fd)
    finally:
        os.close(fd)
    if counts is None:
        pytest.skip("this kernel's serial driver keeps no counters for ttyS0")
    assert set(counts) == set(UartError) and all(n >= 0 for n in counts.values())


def test_uart_errors_are_exported_per_line_and_kind() -> None:
    metrics = GatewayMetrics()
    metrics.watch_uart("a", lambda: {"frame": 3, "parity": 0, "overrun": 1, "break": 0})
    metrics.watch_uart("pty", lambda: None)  # no counters: no series
    text = generate_latest(metrics.registry).decode()
    assert 'modbus_gateway_uart_errors_total{kind="frame",line="a"} 3.0' in text
    assert 'modbus_gateway_uart_errors_total{kind="overrun",line="a"} 1.0' in text
    assert 'line="pty"' not in text
