"""Status vocabulary and pure helpers: histogram quantiles, trace filters, the IP checksum."""

from __future__ import annotations

import ipaddress
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.io.http.live import TraceEvent, TraceFilter
from gateway.io.status import (
    GatewayStatus,
    LineState,
    LineStatus,
    MasterStatus,
    SlaveState,
    SlaveStatus,
    quantile,
    to_json,
)
from gateway.pcap import ip_tcp_segment

BOUNDS = (0.001, 0.01, 0.1)


def test_quantile_interpolates_within_the_bucket_as_prometheus_does() -> None:
    assert quantile(BOUNDS, [0, 0, 0, 0], 0.5) is None
    assert quantile(BOUNDS, [0, 10, 0, 0], 0.5) == pytest.approx(0.0055)  # half of 1..10 ms
    assert quantile(BOUNDS, [10, 0, 0, 0], 0.5) == pytest.approx(0.0005)
    assert quantile(BOUNDS, [0, 0, 0, 4], 0.99) == 0.1  # in +Inf: the highest bound
    assert quantile(BOUNDS, [99, 0, 1, 0], 0.99) == pytest.approx(0.001)
    assert quantile(BOUNDS, [98, 0, 2, 0], 0.99) == pytest.approx(0.055)


@given(st.lists(st.integers(0, 50), min_size=4, max_size=4), st.floats(0, 1), st.floats(0, 1))
def test_quantile_grows_with_q(counts: list[int], q1: float, q2: float) -> None:
    low, high = sorted((q1, q2))
    a, b = quantile(BOUNDS, counts, low), quantile(BOUNDS, counts, high)
    if sum(counts) == 0:
        assert a is None and b is None
    else:
        assert a is not None and b is not None and 0 <= a <= b <= BOUNDS[-1]


def test_status_serialises_enums_as_their_words() -> None:
    status = GatewayStatus(
        "1", 2.0,
        (LineStatus("a", "serial", "/dev/ttyUSB0", LineState.NOISY, 3,
                    slaves=(SlaveStatus("a", 5, SlaveState.SUSPECT, errors=2),)),),
        (MasterStatus("10.0.0.7:5000", "0.0.0.0:502", 1, 9),),
    )  # fmt: skip
    plain = to_json(status)
    assert plain["lines"][0]["state"] == "noisy"
    assert plain["lines"][0]["slaves"][0] == {
        "line": "a", "unit": 5, "state": "suspect", "p50": None, "p99": None, "errors": 2,
        "units": [], "name": None, "heard": False, "requests": 0, "exceptions": {},
        "timeouts": 0, "crc_errors": 0, "last_seen": None,
        "learned_timeout": None,
    }  # fmt: skip
    assert plain["masters"][0]["peer"] == "10.0.0.7:5000"


def _event(**fields: object) -> TraceEvent:
    base: dict[str, object] = {
        "time": 0.0, "direction": "reply", "master": "10.0.0.7:5000", "transaction_id": 1,
        "unit": 100, "function": 3, "pdu": b"\x03\x02\x00\x01", "line": "a", "slave": 1,
        "outcome": "ok",
    }  # fmt: skip
    base.update(fields)
    return TraceEvent(**base)  # type: ignore[arg-type]


def test_trace_filters_from_the_query_string() -> None:
    only = TraceFilter.from_query(
        {"unit": ["100,101"], "function": ["read_holding_registers"], "master": ["10.0.0.7"],
         "line": ["a"], "outcome": ["ok"]}
    )  # fmt: skip
    assert only.matches(_event())
    assert only.matches(_event(function=0x83))  # an exception to a read: still function 3
    assert not only.matches(_event(unit=7))
    assert not only.matches(_event(line="b"))
    assert not only.matches(_event(outcome="target_failed"))
    assert not only.matches(_event(direction="request", outcome=None))  # outcome: replies only
    assert not only.matches(_event(master="10.0.0.77:5000"))
    assert TraceFilter.from_query({"master": ["10.0.0.7:5000"]}).matches(_event())
    assert not TraceFilter.from_query({"master": ["10.0.0.7:5001"]}).matches(_event())
    assert TraceFilter.from_query({}).matches(_event(line=None, slave=None))
    for query, message in (
        ({"unit": ["300"]}, "unit=300"),
        ({"function": ["read_everything"]}, "function='read_everything'"),
        ({"outcome": ["fine"]}, "outcome=fine: expected one of"),
    ):
        with pytest.raises(ValueError, match=message):
            TraceFilter.from_query(query)


def _ones_complement_sum(data: bytes) -> int:
    total: int = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return total


def test_synthesised_segments_carry_valid_checksums() -> None:
    src, dst = ipaddress.ip_address("10.0.0.7"), ipaddress.ip_address("10.0.0.1")
    payload = bytes.fromhex("0001 0000 0006 01 03 0000 000A")
    packet = ip_tcp_segment(src, 5000, dst, 502, 1, 1, payload)
    assert _ones_complement_sum(packet[:20]) == 0xFFFF  # the IPv4 header checksum verifies
    tcp = packet[20:]
    pseudo = src.packed + dst.packed + struct.pack("!BBH", 0, 6, len(tcp))
    assert _ones_complement_sum(pseudo + tcp + b"\0" * (len(tcp) % 2)) == 0xFFFF
    assert struct.unpack("!HH", tcp[:4]) == (5000, 502) and tcp[20:] == payload
