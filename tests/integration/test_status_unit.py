"""The status unit (agent mode) on a running gateway: raw Modbus TCP and RTU over TCP in,
a simulated RTU line on a real pty out.

The gateway polls its ``[[poll]]`` blocks itself; the status unit's registers are read
by masters as any unit's, through the same admission, and say each block's age (tenths
of a second, 65535 never polled) and state (0 fresh, 1 stale, 2 failing).
"""

from __future__ import annotations

import struct
from typing import Any

from gateway.config import build_config
from gateway.sim import UnitFaults, open_pty_pair, plc
from gateway.sim.pki import Pki
from tests.helpers import (
    GatewayFactory,
    RawClient,
    RunningGateway,
    SimBus,
    SimFactory,
    client_context,
    h,
    read,
    wait_until,
)
from tests.integration.test_rtu_over_tcp_listener import RtuClient, listener_address
from tests.integration.test_security import listener_address as tls_address
from tests.integration.test_security import tls_listener
from tests.integration.test_serial_slave import RtuMaster

STATUS = 250


def registers(pdu: bytes) -> list[int]:
    """The values of a normal read answer."""
    assert pdu[0] in (3, 4) and pdu[1] == len(pdu) - 2, pdu.hex(" ")
    return list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


def tables(sim: SimBus, **extra: Any) -> dict[str, Any]:
    """Line ``a`` with slaves 1 and 2 (2 never answers), three blocks, the status unit."""
    raw: dict[str, Any] = {
        "lines": {"a": sim.line_table([1, 2], timeout=0.1, retries=0)},
        "poll": [
            {"unit": 1, "function": 3, "address": 0, "count": 10, "every": 0.05, "max_age": 0.5},
            {"unit": 2, "function": 3, "address": 0, "count": 2, "every": 0.05, "max_age": 0.5},
            {"unit": 1, "function": 4, "address": 0, "count": 4, "every": 0.05, "max_age": 0.5},
        ],
        "polling": {"status_unit": STATUS},
    }
    raw.update(extra)
    return raw


def start(
    make_sim: SimFactory, make_gateway: GatewayFactory, **extra: Any
) -> tuple[SimBus, RunningGateway]:
    sim = make_sim({1: plc(1)})  # unit 2 is absent: its block never gets an answer
    return sim, make_gateway(tables(sim, **extra))


def status(client: RawClient, count: int = 6) -> list[int]:
    return registers(client.request(STATUS, read(0, count)))


def requests_total(gateway: RunningGateway, outcome: str, function: str) -> float:
    labels = {"line": "status", "unit": str(STATUS), "function": function, "outcome": outcome}
    value = gateway.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_requests_total", labels
    )
    return 0.0 if value is None else value


def test_the_status_unit_says_each_blocks_age_and_state_in_configuration_order(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim, gateway = start(make_sim, make_gateway)
    with gateway.connect() as client:
        # Fresh once polled: ages in tenths within max_age (5 tenths), state 0. The block of
        # the absent slave 2 was never answered: 65535, and failing once its poll timed out.
        wait_until(
            lambda: [status(client)[i] for i in (1, 2, 3, 5)] == [0, 0xFFFF, 2, 0],
            "blocks 0 and 2 fresh, block 1 failing and never polled",
        )
        ages = status(client)[0::2]
        assert ages[0] <= 5 and ages[2] <= 5
        # FC 4 reads the same registers; a sub-range starting inside a block too.
        assert registers(client.request(STATUS, read(3, 2, 4)))[0] == 2
        assert registers(client.request(STATUS, read(3, 2, 4)))[1] <= 5
        # Past the last register (3 blocks: 6 registers): 02. A bad count: 03.
        assert client.request(STATUS, read(5, 2)) == h("83 02")
        assert client.request(STATUS, read(6, 1, 4)) == h("84 02")
        assert client.request(STATUS, read(0, 0)) == h("83 03")
        assert client.request(STATUS, read(0, 126)) == h("83 03")
        # Anything but FC 3 and FC 4, writes included: 01. None reaches the line.
        sent = sim.stats().requests
        assert client.request(STATUS, h("06 0000 0001")) == h("86 01")
        assert client.request(STATUS, h("10 0000 0001 02 0001")) == h("90 01")
        assert client.request(STATUS, read(0, 8, 1)) == h("81 01")
        assert client.request(STATUS, h("2B 0E 01 00")) == h("AB 01")
        assert sim.stats().requests - sent <= 3 * 20  # only the plan's polls went meanwhile
        # The slave stops answering: block 0 turns failing, its age grows past max_age.
        sim.faults(1).silent = True
        wait_until(lambda: status(client)[1] == 2, "block 0 failing")
        wait_until(lambda: status(client)[0] > 5, "block 0 older than its max_age")
        assert status(client)[0] != 0xFFFF  # it was polled once: an age, not "never"
    assert requests_total(gateway, "ok", "read_holding_registers") >= 4
    assert requests_total(gateway, "slave_exception", "write_single_register") == 1
    assert requests_total(gateway, "slave_exception", "read_input_registers") == 1


def test_a_stale_block_turns_fresh_when_its_slave_answers_again(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)}, faults={1: UnitFaults(silent=True)})
    gateway = make_gateway(tables(sim))
    with gateway.connect() as client:
        wait_until(lambda: status(client)[:2] == [0xFFFF, 2], "block 0 failing, never polled")
        sim.faults(1).silent = False
        wait_until(lambda: status(client)[1] == 0, "block 0 fresh")
        assert status(client)[0] <= 5


def test_the_access_rules_apply_to_the_status_unit_by_its_unit_id(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    # Rules that grant slave 1, and every slave of line a: none lists unit 250.
    rules = [{"units": [1]}, {"line": "a", "access": "read"}]
    sim, gateway = start(
        make_sim, make_gateway, server={"policy": "p"}, policies={"p": {"rules": rules}}
    )
    with gateway.connect() as client:
        assert client.request(STATUS, read(0, 2)) == h("83 01")
        assert client.request(1, read(0))[:2] == h("03 02")
    # A rule that lists the unit grants it (its writes: 01, denied by the rule as well).
    granted = [{"units": [1]}, {"units": [STATUS], "access": "read"}]
    server = {"listen": "127.0.0.1:0", "policy": "p"}
    raw = tables(sim, server=server, policies={"p": {"rules": granted}})
    gateway.run(gateway.gateway.reload(build_config(raw, "<test>")))
    with gateway.connect() as client:
        assert len(registers(client.request(STATUS, read(0, 2)))) == 2
        assert client.request(STATUS, h("06 0000 0001")) == h("86 01")


def test_a_reload_moves_the_status_unit_and_keeps_what_it_reads(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim, gateway = start(make_sim, make_gateway)
    with gateway.connect() as client:
        wait_until(lambda: status(client)[1] == 0, "block 0 fresh")
    raw = tables(sim, server={"listen": "127.0.0.1:0"}, polling={"status_unit": 251})
    gateway.run(gateway.gateway.reload(build_config(raw, "<test>")))
    with gateway.connect() as client:
        assert client.request(STATUS, read(0, 2)) == h("83 0A")  # no longer routed
        age, state = registers(client.request(251, read(0, 2)))
        assert state == 0 and age <= 5  # the new status unit reads the same blocks
    raw = tables(sim, server={"listen": "127.0.0.1:0"}, polling={"status_unit": 0})
    gateway.run(gateway.gateway.reload(build_config(raw, "<test>")))
    with gateway.connect() as client:
        assert client.request(251, read(0, 2)) == h("83 0A")  # off


def test_rtu_over_tcp_masters_read_the_status_unit_too(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    listener = {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0"}
    _sim, gateway = start(make_sim, make_gateway, listeners=[listener])
    client = RtuClient(listener_address(gateway))
    try:
        fresh = h("03 02 0000")
        wait_until(lambda: client.request(STATUS, read(1), 4) == fresh, "block 0 fresh")
        assert client.request(STATUS, h("06 0001 0000"), 2) == h("86 01")
        assert client.request(STATUS, read(6), 2) == h("83 02")
    finally:
        client.close()


def test_serial_masters_read_the_status_unit_through_a_serial_slave_listener(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    pair = open_pty_pair()
    try:
        listener = {"name": "field", "protocol": "serial-slave", "device": pair.path}
        _sim, gateway = start(make_sim, make_gateway, listeners=[listener])
        (slave,) = gateway.gateway.serial_slaves
        wait_until(lambda: gateway.call(lambda: slave.up), "the serial-slave line open")
        master = RtuMaster(pair.sim_fd)
        fresh = h("03 02 0000")
        wait_until(lambda: master.request(STATUS, read(1), 4) == fresh, "block 0 fresh")
        assert master.request(STATUS, h("06 0001 0000"), 2) == h("86 01")
        assert master.request(STATUS, read(6, 1, 4), 2) == h("84 02")
    finally:
        pair.close()


def test_tls_masters_read_the_status_unit_as_their_role_allows(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> None:
    # Operators may read unit 1; viewers unit 1 and the status unit.
    rules = [
        {"role": "operator", "units": [1]},
        {"role": "viewer", "units": [1, STATUS], "access": "read"},
    ]
    listener = tls_listener(pki, policy="plant")
    _sim, gateway = start(
        make_sim, make_gateway, listeners=[listener], policies={"plant": {"rules": rules}}
    )
    address = tls_address(gateway, "tls")
    with (
        RawClient(address, context=client_context(pki, "viewer")) as viewer,
        RawClient(address, context=client_context(pki, "operator")) as operator,
    ):
        wait_until(lambda: status(viewer)[1] == 0, "block 0 fresh, read over TLS")
        assert viewer.request(STATUS, h("06 0000 0001")) == h("86 01")  # its rule: reads only
        assert operator.request(STATUS, read(0, 2)) == h("83 01")  # no rule names it
        assert operator.request(1, read(0))[:2] == h("03 02")
