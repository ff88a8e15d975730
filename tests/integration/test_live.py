"""The live trace stream and ``GET /status`` on a running gateway, over real HTTP on loopback."""

from __future__ import annotations

import json
import socket
import ssl
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from gateway.io.http import live
from gateway.io.http.live import QUEUE_LIMIT
from gateway.sim import plc
from gateway.sim.pki import make_pki
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    GatewayOnSim,
    RunningGateway,
    SimFactory,
    wait_until,
)
from tests.integration.metrics_harness import http_get, metrics_address, samples, series

READ_10 = bytes.fromhex("03 0000 000A")


class Stream:
    """A raw HTTP client on ``GET /trace``: reads events only when asked."""

    def __init__(self, gw: RunningGateway, query: str = "", receive_buffer: int = 0) -> None:
        self.sock = socket.socket()
        if receive_buffer:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.settimeout(DEADLINE_S)
        self.sock.connect(metrics_address(gw))
        self.sock.sendall(f"GET /trace{query} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        self.buffer = b""
        head = self._until(b"\r\n\r\n")
        self.status = int(head.split()[1])
        self.head = head.decode("latin-1")

    def _until(self, marker: bytes) -> bytes:
        while marker not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise AssertionError(f"stream closed; had {self.buffer[-200:]!r}")
            self.buffer += chunk
        data, _, self.buffer = self.buffer.partition(marker)
        return data

    def event(self) -> dict[str, Any]:
        """The next event."""
        event: dict[str, Any] = json.loads(self._until(b"\n"))
        return event

    def close(self) -> None:
        self.sock.close()


@contextmanager
def stream(gw: RunningGateway, query: str = "", receive_buffer: int = 0) -> Iterator[Stream]:
    client = Stream(gw, query, receive_buffer)
    try:
        assert client.status == 200, client.head
        # The stream is registered before its head is sent: events from now on reach it.
        yield client
    finally:
        client.close()


def status(gw: RunningGateway) -> dict[str, Any]:
    code, headers, body = http_get(gw, "/status")
    assert code == 200 and headers["content-type"] == "application/json"
    result: dict[str, Any] = json.loads(body)
    return result


def test_the_stream_shows_hex_and_where_a_remapped_unit_went(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1), 2: plc(2)}, routes=[{"unit": 100, "line": "a", "slave": 2}])
    with stream(gw, "?unit=100") as trace, gw.connect() as master:
        master.request(1, READ_10)  # another unit: filtered out by the gateway
        tid = master.send(100, READ_10)
        reply = master.receive()
        request_event, reply_event = trace.event(), trace.event()
        peer = "{}:{}".format(*master.sock.getsockname())
    assert request_event == {
        **request_event,
        "type": "request", "tid": tid, "unit": 100, "line": "a", "slave": 2,
        "function": "read_holding_registers", "fc": 3, "hex": "03 00 00 00 0a",
        "detail": "address=0 quantity=10",
    }  # fmt: skip
    assert request_event["master"] == peer
    assert reply_event["type"] == "reply" and reply_event["tid"] == tid
    assert (reply_event["line"], reply_event["slave"], reply_event["outcome"]) == ("a", 2, "ok")
    assert bytes.fromhex(reply_event["hex"]) == reply.pdu
    assert reply_event["latency_ms"] > 0


def test_filters_by_line_function_outcome_and_master(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line={"timeout": 0.05, "retries": 0})
    sim.faults(2).silent = True
    with (
        stream(gw, "?outcome=target_failed") as failed,
        stream(gw, "?function=write_single_register&line=a") as writes,
        stream(gw, "?master=127.0.0.2") as other_master,
        gw.connect() as master,
    ):
        master.request(1, READ_10)
        master.request(1, bytes.fromhex("06 0001 0007"))
        master.request(2, READ_10)
        event = failed.event()
        assert (event["type"], event["unit"], event["outcome"]) == ("reply", 2, "target_failed")
        request, reply = writes.event(), writes.event()
        assert (request["fc"], reply["fc"], reply["outcome"]) == (6, 6, "ok")
        assert reply["detail"] == "address=1 value=0x0007"
        with socket.socket() as sock:
            sock.bind(("127.0.0.2", 0))
            sock.settimeout(DEADLINE_S)
            sock.connect(gw.address)
            sock.sendall(bytes.fromhex("0009 0000 0006 01") + READ_10)
            sock.recv(256)
        event = other_master.event()
        assert event["tid"] == 9 and event["master"].startswith("127.0.0.2:")


def test_a_bad_filter_is_refused_with_the_reason(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    code, _headers, body = http_get(gw, "/trace?unit=abc")
    assert code == 400 and b"unit='abc'" in body
    code, _headers, body = http_get(gw, "/trace?outcome=fine")
    assert code == 400 and b"expected one of" in body and b"target_failed" in body


@pytest.mark.slow  # fills a stalled client's socket buffers under load, ~4 s
def test_a_client_that_does_not_read_loses_events_not_the_gateways_time(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    dropped = series("modbus_gateway_trace_dropped_events_total")
    with stream(gw, receive_buffer=4096) as slow, gw.connect() as master:
        # Every request makes two events of ~250 bytes: far more than the kernel and
        # process buffers plus the stream's queue of QUEUE_LIMIT events can hold.
        answered = 0
        started = time.monotonic()
        while samples(gw).get(dropped, 0.0) == 0.0:
            assert time.monotonic() - started < 3 * DEADLINE_S, "no events were dropped"
            for _ in range(8):  # pipelined, as a busy master would
                master.send(1, READ_10)
            for _ in range(8):
                assert master.receive().pdu[:2] == b"\x03\x14"
                answered += 1
        assert answered >= QUEUE_LIMIT // 2
        # The slow client finally reads: it is told how much it lost, then gets new events.
        slow.sock.settimeout(DEADLINE_S)
        gap = None
        while gap is None:
            event = slow.event()
            if event["type"] == "gap":
                gap = event
        assert gap["dropped"] > 0
        assert samples(gw)[dropped] >= gap["dropped"]
    assert status(gw)["trace_dropped"] >= gap["dropped"]


def test_status_reports_lines_slaves_and_masters(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        line={
            "timeout": 0.05,
            "retries": 0,
            "dead_after": 2,
            "probe_interval": 60,
            "late_answer_window": 0,
        },  # silent: nothing comes late
    )
    first = status(gw)
    (line,) = first["lines"]
    assert (line["name"], line["kind"], line["device"], line["state"]) == (
        "a", "serial", sim.path, "up",
    )  # fmt: skip
    assert [(s["unit"], s["state"], s["errors"]) for s in line["slaves"]] == [
        (1, "up", 0), (2, "up", 0),
    ]  # fmt: skip
    assert first["masters"] == []
    with gw.connect() as master:
        for _ in range(5):
            master.request(1, READ_10)
        sim.faults(2).silent = True
        master.request(2, READ_10)  # one timeout: suspect
        now = status(gw)
        slaves = {s["unit"]: s for s in now["lines"][0]["slaves"]}
        assert slaves[2]["state"] == "suspect" and slaves[2]["errors"] == 1
        assert slaves[1]["state"] == "up"
        assert 0 < slaves[1]["p50"] <= slaves[1]["p99"] < 1.0
        assert now["lines"][0]["utilisation"] is not None
        assert now["lines"][0]["p50"] is not None
        (entry,) = now["masters"]
        assert entry["peer"] == "{}:{}".format(*master.sock.getsockname())
        assert entry["requests"] == 6 and entry["in_flight"] == 0
        assert entry["listener"].endswith(f":{gw.port}")
        master.request(2, READ_10)  # the second timeout in a row: isolated
        slaves = {s["unit"]: s for s in status(gw)["lines"][0]["slaves"]}
        assert slaves[2]["state"] == "down" and slaves[2]["errors"] == 2


def test_status_shows_a_line_down(make_gateway: GatewayFactory, tmp_path: Path) -> None:
    device = str(tmp_path / "ttyUSB9")  # an adapter that is not plugged in
    gw = make_gateway({"lines": {"a": {"device": device, "units": [1]}}})
    (line,) = status(gw)["lines"]
    assert (line["name"], line["device"], line["state"]) == ("a", device, "down")


def test_the_page_is_self_contained(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    code, headers, body = http_get(gw, "/")
    assert code == 200 and headers["content-type"].startswith("text/html")
    page = body.decode()
    assert "<script>" in page and "fetch(" in page and "EventSource(" in page
    for external in ("http://", "https://", "//cdn", "@import", "src=", '<link rel="style'):
        assert external not in page, external


def test_quiet_streams_get_heartbeats_and_sse_frames_events(
    gateway_with: GatewayOnSim, monkeypatch: pytest.MonkeyPatch
) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    monkeypatch.setattr(live, "HEARTBEAT_S", 0.05)
    with stream(gw) as ndjson:
        assert ndjson.event() == {"type": "heartbeat"}
    with stream(gw, "?format=sse") as sse, gw.connect() as master:
        assert "content-type: text/event-stream" in sse.head.lower()
        assert sse._until(b"\n\n") == b": modbus-gateway trace"
        assert sse._until(b"\n\n") == b": keep-alive"
        master.request(1, READ_10)
        frame = sse._until(b"\n\n")
        while frame == b": keep-alive":
            frame = sse._until(b"\n\n")
        assert frame.startswith(b"data: ")
        assert json.loads(frame[6:])["type"] == "request"


def test_streams_past_the_cap_are_refused(
    gateway_with: GatewayOnSim, monkeypatch: pytest.MonkeyPatch
) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    monkeypatch.setattr(live, "MAX_STREAMS", 2)
    with stream(gw), stream(gw):
        refused = Stream(gw)
        assert (
            refused.status == 503
            and "2 trace streams are open already" in refused._until(b"\n").decode()
        )
        refused.close()
    with stream(gw) as again:  # closed streams free their places
        assert again.status == 200
    wait_until(lambda: status(gw)["trace_clients"] == 0, "the closed streams to be forgotten")


def test_masters_on_every_listener_are_traced_and_listed(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    pki = make_pki(tmp_path)
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "lines": {"a": sim.line_table([1])},
        "listeners": [{"name": "tls", "protocol": "tls", "listen": "127.0.0.1:0",
                       "cert": str(pki.server_chain), "key": str(pki.server_key),
                       "ca": str(pki.ca)}],
    })  # fmt: skip
    tls_address = gw.call(lambda: gw.gateway.listener_address("tls"))
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=str(pki.ca))
    context.load_cert_chain(*pki.client("operator"))
    with (
        stream(gw, "?unit=1") as trace,
        gw.connect() as plain,
        context.wrap_socket(socket.create_connection(tls_address, timeout=DEADLINE_S),
                            server_hostname="localhost") as secure,
    ):  # fmt: skip
        secure.sendall(bytes.fromhex("0007 0000 0006 01") + READ_10)
        assert secure.recv(256)[:2] == b"\x00\x07"
        event = trace.event()
        assert (event["tid"], event["type"]) == (7, "request")
        assert event["master"] == "{}:{}".format(*secure.getsockname())
        assert (event["listener"], event["role"]) == ("tls", "operator")
        plain.request(1, READ_10)
        listeners = sorted(m["listener"].split()[0] for m in status(gw)["masters"])
        assert listeners == ["tcp", "tls"]


def test_a_line_with_fresh_crc_errors_shows_noisy(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line={"retries": 3})
    assert status(gw)["lines"][0]["state"] == "up"  # the first refresh: the baseline
    sim.faults(1).crc_error_rate = 0.5
    with gw.connect() as master:
        while sim.stats().crc_errors_out == 0:
            master.request(1, READ_10)
    assert status(gw)["lines"][0]["state"] == "noisy"
    assert status(gw)["lines"][0]["state"] == "up"  # no new errors since the last refresh


def test_status_lists_slaves_by_unit_id_with_names_counts_and_masters_denials(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1), 2: plc(2)})
    line = sim.line_table([1, 2, 3], timeout=0.05, retries=0, late_answer_window=0,
                          names={"2": "meter"})  # fmt: skip
    gw = make_gateway({
        "server": {"policy": "readers"},
        "policies": {"readers": {"rules": [{"units": [1, 2, 3, 100, 200], "access": "read"}]}},
        "lines": {"a": line},
        "routes": [{"unit": 100, "line": "a", "slave": 2}],
    })  # fmt: skip
    (before,) = status(gw)["lines"]
    assert before["not_heard"] == 3 and before["settings"].startswith("rtu 115200 8N1")
    assert before["uart_errors"] is None  # a pty keeps no UART error counters
    assert before["fair_turn_s"] is None  # nothing answered yet: no turn learned
    named = {s["unit"]: s for s in before["slaves"]}[2]
    assert (named["name"], named["units"], named["heard"]) == ("meter", [2, 100], False)
    round_trips: list[float] = []
    with gw.connect() as master, stream(gw, "?unit=1") as trace:
        started = time.monotonic()
        assert master.request(1, READ_10)[:2] == b"\x03\x14"
        round_trips.append(time.monotonic() - started)
        assert master.request(1, bytes.fromhex("03 FFF0 0001")) == b"\x83\x02"
        assert master.request(1, bytes.fromhex("06 0001 0001")) == b"\x86\x01"  # denied
        assert master.request(200, READ_10) == b"\x83\x0a"  # allowed, but no route
        started = time.monotonic()
        assert master.request(100, READ_10)[:2] == b"\x03\x14"
        round_trips.append(time.monotonic() - started)
        sim.faults(2).silent = True
        assert master.request(100, READ_10) == b"\x83\x0b"  # a timeout
        reply = trace.event()
        while reply["type"] != "reply":
            reply = trace.event()
        assert reply["values"] == {"address": 0, "registers": reply["values"]["registers"]}
        assert len(reply["values"]["registers"]) == 10
        exception = trace.event()
        while exception["type"] != "reply":
            exception = trace.event()
        assert exception["values"] == {"exception": 2, "name": "illegal data address"}
        now = status(gw)
        (entry,) = now["masters"]
        assert (entry["denied"], entry["role"], entry["requests"]) == (1, None, 6)
        assert entry["unrouted"] == 1 and now["unrouted"] == 1
    (after,) = now["lines"]
    slaves = {s["unit"]: s for s in after["slaves"]}
    one, two = slaves[1], slaves[2]
    assert (one["units"], one["requests"], one["exceptions"], one["heard"]) == (
        [1], 2, {"2": 1}, True,
    )  # fmt: skip
    assert abs(one["last_seen"] - now["time"]) < DEADLINE_S
    assert (two["requests"], two["timeouts"], two["crc_errors"], two["errors"]) == (2, 1, 0, 1)
    assert after["not_heard"] == 1  # slave 3 never answered
    assert "read_holding_registers" in now["functions"]
    assert after["history_s"] == live.HISTORY_S and isinstance(after["history"], list)
    assert after["unavailable"] == 0  # the line was up and had room
    assert 0 < after["latency_window_s"] <= live.LATENCY_WINDOW_S  # since the first look
    # One turn is the typical answered transaction (a read of 10 registers at 115200 baud and
    # the silence after it), the timeout no answer: within a few of the reads' round trips.
    assert min(round_trips) / 5 <= after["fair_turn_s"] <= 5 * max(round_trips), round_trips
