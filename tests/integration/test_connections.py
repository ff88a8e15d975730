"""TCP limits: the connection cap (evict the oldest idle master, or refuse), the idle timeout."""

from __future__ import annotations

from gateway.sim import plc
from tests.helpers import DEADLINE_S, GatewayOnSim, RawClient

READ_1 = bytes.fromhex("03 0000 0001")


def test_at_the_limit_the_oldest_idle_master_makes_room(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, server={"max_connections": 2, "evict_min_idle": 0.0})
    oldest, newer = gw.connect(), gw.connect()
    try:
        assert oldest.request(1, READ_1)[0] == 0x03
        assert newer.request(1, READ_1)[0] == 0x03  # newer is now the most recently active
        with gw.connect() as third:
            assert third.request(1, READ_1)[0] == 0x03
            assert oldest.is_closed_by_peer(DEADLINE_S)
            assert newer.request(1, READ_1)[0] == 0x03
        evicted = gw.gateway.metrics.registry.get_sample_value(
            "modbus_gateway_connections_closed_total", {"reason": "evicted"}
        )
        assert evicted == 1
    finally:
        oldest.close()
        newer.close()


def test_at_the_limit_a_new_master_is_refused_when_configured(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)}, server={"max_connections": 1, "when_full": "refuse"})
    with gw.connect() as first:
        assert first.request(1, READ_1)[0] == 0x03
        refused = RawClient(gw.address)
        try:
            assert refused.is_closed_by_peer(DEADLINE_S)
        finally:
            refused.close()
        assert first.request(1, READ_1)[0] == 0x03  # the first master is untouched
    rejected = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_connections_rejected_total", {"reason": "max_connections"}
    )
    assert rejected == 1


def test_an_idle_master_is_disconnected_and_a_busy_one_is_not(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        server={"idle_timeout": 0.3},
        line={"timeout": 2.0, "retries": 0, "dead_after": 0},
    )
    sim.faults(2).silent = True
    with gw.connect() as idle, gw.connect() as waiting:
        assert idle.request(1, READ_1)[0] == 0x03
        tid = waiting.send(2, READ_1)  # in flight for 2 s, longer than the idle timeout
        assert idle.is_closed_by_peer(DEADLINE_S)
        reply = waiting.receive(timeout=DEADLINE_S)
        assert (reply.transaction_id, reply.pdu) == (tid, bytes([0x83, 0x0B]))
    closed = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_connections_closed_total", {"reason": "idle"}
    )
    assert closed == 1
