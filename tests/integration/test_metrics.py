"""Each fault increments exactly the right series: a real gateway, a simulated line on a pty.

Every test compares two scrapes of /metrics and checks the whole set of fault
counters that changed, so a fault counted twice, or under the wrong label, or
in a second family too, fails as surely as one not counted at all.
"""

from __future__ import annotations

import socket

from prometheus_client.parser import text_string_to_metric_families

from gateway import __version__, build
from gateway.sim import plc
from tests.helpers import GatewayFactory, GatewayOnSim, RawClient, SimFactory, mbap, wait_until
from tests.integration.metrics_harness import (
    Series,
    counter_changes,
    http_get,
    increase,
    metrics_address,
    samples,
    series,
    value,
)

#: The families a fault may touch; each test pins down which of them change, and by how much.
FAULT_FAMILIES = (
    "modbus_gateway_requests",
    "modbus_gateway_crc_errors",
    "modbus_gateway_timeouts",
    "modbus_gateway_retries",
    "modbus_gateway_discarded_frames",
    "modbus_gateway_protocol_errors",
)
READ_10 = bytes.fromhex("03 0000 000A")
SENT = series("modbus_gateway_rtu_frames_sent_total", line="a")
FAST = {"timeout": 0.05, "retries": 1}


def requests(
    line: str, unit: str, outcome: str, function: str = "read_holding_registers"
) -> Series:
    return series(
        "modbus_gateway_requests_total", line=line, unit=unit, function=function, outcome=outcome
    )


def per_unit(name: str, unit: str, line: str = "a") -> Series:
    return series(f"modbus_gateway_{name}_total", line=line, unit=unit)


def heard(master: RawClient, *units: int) -> None:
    """One good read from each unit: ``requests_total`` names a slave once it has answered."""
    for unit in units:
        assert master.request(unit, READ_10)[0] == 0x03


def test_ok_request_counts_once_and_observes_every_histogram(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=FAST)
    with gw.connect() as master:
        before = samples(gw)
        answer = master.request(1, READ_10)
        after = samples(gw)
    assert answer == bytes.fromhex("03 14 0000 0002 0004 0006 0008 000A 0000 0000 0000 0000")
    assert counter_changes(before, after, FAULT_FAMILIES) == {requests("a", "1", "ok"): 1}
    assert increase(before, after, SENT) == 1
    assert increase(before, after, series("modbus_gateway_rtu_frames_received_total", line="a"))
    for histogram in ("request_duration", "wire_duration", "queue_wait"):
        count = series(f"modbus_gateway_{histogram}_seconds_count", line="a")
        assert increase(before, after, count) == 1, histogram
    written = series("modbus_gateway_serial_written_bytes_total", line="a")
    read = series("modbus_gateway_serial_read_bytes_total", line="a")
    assert increase(before, after, written) == 8  # unit, 5-byte PDU, CRC
    assert increase(before, after, read) == 25  # unit, 22-byte PDU, CRC


def test_crc_error_is_retried_then_answered_0x0b(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line=FAST)
    with gw.connect() as master:
        heard(master, 1)
        sim.faults(1).crc_error_rate = 1.0
        before = samples(gw)
        assert master.request(1, READ_10) == bytes((0x83, 0x0B))
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        per_unit("crc_errors", "1"): 2,
        per_unit("retries", "1"): 1,
        requests("a", "1", "target_failed"): 1,
    }
    assert increase(before, after, SENT) == 2


def test_timeout_is_retried_then_answered_0x0b(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line=FAST)
    with gw.connect() as master:
        heard(master, 2)
        sim.faults(2).silent = True
        before = samples(gw)
        assert master.request(2, READ_10) == bytes((0x83, 0x0B))
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        per_unit("timeouts", "2"): 2,
        per_unit("retries", "2"): 1,
        requests("a", "2", "target_failed"): 1,
    }
    # The healthy unit's series exist at 0 from the start, so rate() sees its first fault.
    assert after[per_unit("timeouts", "1")] == 0


def test_late_answer_after_a_timeout_is_discarded(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 0.05, "retries": 0})
    late = series("modbus_gateway_discarded_frames_total", line="a", reason="late")
    with gw.connect() as master:
        heard(master, 1)
        sim.faults(1).reply_delay = 0.1
        before = samples(gw)
        assert master.request(1, READ_10) == bytes((0x83, 0x0B))
        wait_until(lambda: value(gw, late) >= 1, "the late answer to be discarded")
        changes = counter_changes(before, samples(gw), FAULT_FAMILIES)
    assert changes.pop(late) >= 1  # one answer, read in one chunk or more
    assert changes == {per_unit("timeouts", "1"): 1, requests("a", "1", "target_failed"): 1}


def test_answer_from_another_unit_is_discarded(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line=FAST)
    sim.faults(1).wrong_unit_reply = True
    with gw.connect() as master:
        before = samples(gw)
        assert master.request(1, READ_10)[0] == 0x03
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        series("modbus_gateway_discarded_frames_total", line="a", reason="unexpected_unit"): 1,
        requests("a", "1", "ok"): 1,
    }


def test_unit_without_route_is_answered_0x0a_off_the_line(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=FAST)
    with gw.connect() as master:
        before = samples(gw)
        assert master.request(99, READ_10) == bytes((0x83, 0x0A))
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        requests("none", "other", "no_route"): 1
    }
    assert increase(before, after, SENT) == 0


def test_invalid_request_is_rejected_locally(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=FAST)
    with gw.connect() as master:
        before = samples(gw)
        assert master.request(1, bytes.fromhex("03 0000 00C8")) == bytes((0x83, 0x03))  # 200
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        requests("none", "other", "rejected"): 1,
        series("modbus_gateway_protocol_errors_total", kind="invalid_request"): 1,
    }
    assert increase(before, after, SENT) == 0


def test_unknown_function_code_is_labelled_other(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=FAST)
    with gw.connect() as master:
        before = samples(gw)
        assert master.request(1, bytes((0x41, 0x00))) == bytes((0xC1, 0x01))
        after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {
        requests("a", "1", "slave_exception", function="other"): 1
    }


def test_master_leaving_drops_its_queued_requests_unsent(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 1.0})
    dropped = requests("a", "1", "dropped")
    closed = series("modbus_gateway_connections_closed_total", reason="peer_closed")
    master = gw.connect()
    heard(master, 1)
    sim.faults(1).reply_delay = 0.2
    before = samples(gw)
    master.send(1, READ_10)
    wait_until(lambda: sim.stats().requests == 2, "the second request on the wire")
    for address in (0, 0, 20):  # two identical reads (coalesced) and another
        master.send(1, bytes((0x03, 0, address, 0, 10)))
    master.close()
    wait_until(lambda: value(gw, dropped) == 4, "4 requests counted as dropped")
    wait_until(lambda: value(gw, closed) == 1, "the connection counted as closed")
    after = samples(gw)
    assert counter_changes(before, after, FAULT_FAMILIES) == {dropped: 4}
    # Only the request already on the wire was sent: nothing on behalf of a master gone.
    assert increase(before, after, SENT) == 1
    assert after[series("modbus_gateway_queue_depth", line="a")] == 0


def test_connections_accepted_refused_and_closed_by_reason(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, server={"max_connections": 1, "when_full": "refuse"})
    first = gw.connect()
    first.request(1, READ_10)
    assert samples(gw)[series("modbus_gateway_connections_open", listener="tcp")] == 1
    with gw.connect() as second:
        assert second.is_closed_by_peer()
    # A broken MBAP header (protocol id 1) closes that master's connection only.
    first.send_raw(mbap(1, 1, READ_10, protocol_id=1))
    assert first.is_closed_by_peer()
    first.close()
    with gw.connect() as third:
        third.request(1, READ_10)
    closed = series("modbus_gateway_connections_closed_total", reason="peer_closed")
    wait_until(lambda: value(gw, closed) == 1, "the third connection counted as closed")
    after = samples(gw)
    assert after[series("modbus_gateway_connections_accepted_total")] == 2
    rejected = series("modbus_gateway_connections_rejected_total", reason="max_connections")
    assert after[rejected] == 1
    assert after[series("modbus_gateway_connections_open", listener="tcp")] == 0
    reason = series("modbus_gateway_connections_closed_total", reason="protocol_error")
    assert after[reason] == 1
    assert after[series("modbus_gateway_protocol_errors_total", kind="bad_protocol_id")] == 1


def test_health_readiness_and_line_state(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    lines = {
        "a": sim.line_table([1], **FAST),
        "b": {"device": "/dev/no-such-serial-port", "units": [7]},
    }
    gw = make_gateway({"lines": lines})
    assert http_get(gw, "/healthz")[0] == 200
    status, _, body = http_get(gw, "/readyz")
    assert status == 503
    assert body.decode().strip().endswith(": b")  # names the line that is down, only that one
    found = samples(gw)
    assert found[series("modbus_gateway_line_up", line="a")] == 1
    assert found[series("modbus_gateway_line_up", line="b")] == 0
    assert found[series("modbus_gateway_line_info", line="a", kind="rtu")] == 1
    assert found[series("modbus_gateway_line_info", line="b", kind="rtu")] == 1
    info = series("modbus_gateway_build_info", lines="a,b", version=__version__, build=build())
    assert found[info] == 1
    with gw.connect() as master:
        assert master.request(7, READ_10) == bytes((0x83, 0x0A))
    # Unit 7 has never answered: its requests count under unit="other" (bounded labels).
    assert samples(gw)[requests("b", "other", "no_route")] == 1
    assert http_get(gw, "/nope")[0] == 404


def test_ready_when_every_line_is_up(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    assert http_get(gw, "/readyz")[0] == 200


def test_openmetrics_when_the_scraper_asks_for_it(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    accept = "application/openmetrics-text;version=1.0.0,text/plain;version=0.0.4;q=0.5"
    status, headers, body = http_get(gw, "/metrics", accept=accept)
    assert status == 200
    assert headers["content-type"].startswith("application/openmetrics-text")
    assert body.endswith(b"# EOF\n")
    status, headers, body = http_get(gw, "/metrics")
    assert headers["content-type"].startswith("text/plain; version=0.0.4")
    names = {family.name for family in text_string_to_metric_families(body.decode())}
    assert "modbus_gateway_requests" in names


def test_oversized_http_request_head_is_refused(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    with socket.create_connection(metrics_address(gw), timeout=5) as sock:
        sock.sendall(b"GET /metrics HTTP/1.1\r\nX-Junk: " + b"x" * 20000 + b"\r\n\r\n")
        assert sock.recv(64).startswith(b"HTTP/1.1 431")
