"""Fair share at the connection limit, over loopback: 127.0.0.2 and 127.0.0.3 are two hosts.

A SCADA server that opens one connection per device is admitted whole while slots
are free; at the limit the address holding the most connections yields, so a
burst from one host never keeps another host's master out, and a newcomer from
the heaviest host is refused when none of its own connections may go. Connections
that never send a request go before any master at work, under either ``when_full``.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from contextlib import ExitStack, suppress

import pytest

from gateway.sim import UnitFaults, plc
from tests.helpers import DEADLINE_S, GatewayOnSim, RawClient, RunningGateway, wait_until
from tests.integration.metrics_harness import series, value
from tests.integration.test_hostile import HONEST_LINE, HonestMaster, closed_within, connect_from

READ_1 = bytes.fromhex("03 0000 0001")
BURSTY = "127.0.0.2"
OTHER = "127.0.0.3"


class ClientFrom(RawClient):
    """A ``RawClient`` whose connection leaves from the loopback address ``source``."""

    def __init__(self, source: str, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, DEADLINE_S, source_address=(source, 0))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.timeout = DEADLINE_S
        self._next_tid = 1


def rejected(gw: RunningGateway, reason: str) -> float:
    return value(gw, series("modbus_gateway_connections_rejected_total", reason=reason))


def evicted(gw: RunningGateway) -> float:
    return value(gw, series("modbus_gateway_connections_closed_total", reason="evicted"))


def test_a_hundred_connections_from_one_host_are_all_admitted_and_served(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE)  # [server] at its defaults
    with ExitStack() as stack:
        started = time.monotonic()
        clients = [stack.enter_context(gw.connect()) for _ in range(100)]
        tids = [client.send(1, READ_1) for client in clients]
        for client, tid in zip(clients, tids, strict=True):
            reply = client.receive()
            assert (reply.transaction_id, reply.pdu[0]) == (tid, 0x03)
        assert time.monotonic() - started < DEADLINE_S
        server = gw.gateway.server
        assert server is not None and gw.call(lambda: server.connections) == 100
    assert rejected(gw, "max_per_source") == rejected(gw, "max_connections") == 0
    assert evicted(gw) == 0


def test_at_the_limit_the_heaviest_host_yields_to_a_lighter_one_down_to_equal_shares(
    gateway_with: GatewayOnSim,
) -> None:
    # evict_min_idle = 60: no connection is ever old enough; only the share decides.
    _sim, gw = gateway_with(
        {1: plc(1)}, line=HONEST_LINE, server={"max_connections": 8, "evict_min_idle": 60.0}
    )
    with ExitStack() as stack:
        bursty = [stack.enter_context(ClientFrom(BURSTY, gw.address)) for _ in range(8)]
        for client in bursty:  # in order: the first is then the one idle longest
            assert client.request(1, READ_1)[0] == 0x03
        # The heaviest host's newcomer: none of its own is idle for 60 s: refused.
        with ClientFrom(BURSTY, gw.address) as refused:
            assert refused.is_closed_by_peer(DEADLINE_S)
        # The other host's masters get in, each in place of the bursty host's longest-idle,
        # until both hold four: then the bursty host no longer holds two more.
        others = []
        for index in range(4):
            other = stack.enter_context(ClientFrom(OTHER, gw.address))
            assert other.request(1, READ_1)[0] == 0x03
            assert bursty[index].is_closed_by_peer(DEADLINE_S)
            others.append(other)
        with ClientFrom(OTHER, gw.address) as fifth:
            assert fifth.is_closed_by_peer(DEADLINE_S)
        for client in bursty[4:] + others:  # everyone left in is served
            assert client.request(1, READ_1)[0] == 0x03
    assert evicted(gw) == 4
    assert rejected(gw, "max_connections") == 2


@pytest.mark.slow  # about 3 s or more
def test_connections_with_requests_in_flight_are_never_evicted_for_a_lighter_host(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        sim={"faults": {2: UnitFaults(silent=True)}},
        line={"timeout": 3.0, "retries": 0, "dead_after": 0},
        server={"max_connections": 4, "evict_min_idle": 0.0},
    )
    server = gw.gateway.server
    assert server is not None
    with ExitStack() as stack:
        bursty = [stack.enter_context(ClientFrom(BURSTY, gw.address)) for _ in range(4)]
        tids = [client.send(2, READ_1) for client in bursty]  # unit 2 is silent: in flight
        wait_until(
            lambda: gw.call(lambda: sum(m.in_flight > 0 for m in server.masters())) == 4,
            "four requests in flight",
        )
        for source in (OTHER, BURSTY):
            with ClientFrom(source, gw.address) as newcomer:
                assert newcomer.is_closed_by_peer(DEADLINE_S)
        reply = bursty[0].receive(timeout=DEADLINE_S)  # kept: its answer (0x0B) comes
        assert (reply.transaction_id, reply.pdu) == (tids[0], bytes((0x83, 0x0B)))
    assert evicted(gw) == 0
    assert rejected(gw, "max_connections") == 2


def test_bursts_from_one_host_do_not_starve_another_hosts_masters_at_defaults(
    gateway_with: GatewayOnSim,
) -> None:
    limit = 20  # [server] otherwise at its defaults: no cap per address
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE, server={"max_connections": limit})
    stop = threading.Event()
    per_poll_ok: list[bool] = []

    def per_poll_master() -> None:  # connects, polls once, disconnects, like some SCADA drivers
        while not stop.is_set():
            try:
                with ClientFrom(OTHER, gw.address) as client:
                    per_poll_ok.append(client.request(1, READ_1)[0] == 0x03)
            except (OSError, AssertionError):
                per_poll_ok.append(False)

    other = threading.Thread(target=per_poll_master, daemon=True)
    try:
        with HonestMaster(gw) as honest:
            other.start()
            for _ in range(4):  # bursts of more than the whole limit, every 0.5 s
                burst = []
                for _ in range(limit + 10):
                    with suppress(OSError):
                        burst.append(connect_from(BURSTY, gw.address))
                # Past the limit the burst's newcomers are refused (its own are too young
                # to go), and the other host's masters take some of its slots.
                assert closed_within(burst, 10, 0.5) >= 10
                for sock in burst:
                    sock.close()
        honest.check()
    finally:
        stop.set()
        other.join(DEADLINE_S)
    assert per_poll_ok and sum(per_poll_ok) / len(per_poll_ok) >= 0.9, per_poll_ok.count(False)
    assert rejected(gw, "max_connections") >= 20
    assert rejected(gw, "max_per_source") == 0


# --------------------------------------------------------------------------- never-used connections


def _closed_by_peer(sock: socket.socket) -> bool:
    """True when the gateway has closed ``sock`` (EOF or reset); does not wait."""
    if not select.select([sock], [], [], 0.0)[0]:
        return False
    try:
        return sock.recv(1, socket.MSG_DONTWAIT) == b""
    except ConnectionResetError:
        return True


def _silent_bursts(gw: RunningGateway, size: int, bursts: int) -> int:
    """Bursts of ``size`` connections from ``BURSTY`` that never send a byte, each held
    0.5 s; returns how many the gateway closed (refused or evicted)."""
    closed = 0
    for _ in range(bursts):
        burst = []
        for _ in range(size):
            with suppress(OSError):
                burst.append(connect_from(BURSTY, gw.address))
        closed += closed_within(burst, size - 100, 0.5)
        for sock in burst:
            sock.close()
    return closed


@pytest.mark.parametrize(
    "when_full", [pytest.param("close_oldest_idle", marks=pytest.mark.slow), "refuse"]
)
def test_bursts_of_silent_connections_do_not_starve_a_master_connecting_per_poll(
    gateway_with: GatewayOnSim, when_full: str
) -> None:
    # [server] at its defaults (100 connections) but for the policy under test.
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE, server={"when_full": when_full})
    stop = threading.Event()
    per_poll_ok: list[bool] = []

    def per_poll_master() -> None:  # connects, polls once, disconnects, like some SCADA drivers
        while not stop.is_set() and len(per_poll_ok) < 2000:
            try:
                with ClientFrom(OTHER, gw.address) as client:
                    per_poll_ok.append(client.request(1, READ_1)[0] == 0x03)
            except (OSError, AssertionError):
                per_poll_ok.append(False)

    other = threading.Thread(target=per_poll_master, daemon=True)
    try:
        with HonestMaster(gw) as honest:
            other.start()
            # Four bursts of 110 connections that never send a request, every 0.5 s.
            assert _silent_bursts(gw, 110, 4) >= 40  # past the limit, the burst's own go
        honest.check()
    finally:
        stop.set()
        other.join(DEADLINE_S)
    served = sum(per_poll_ok) / len(per_poll_ok) if per_poll_ok else 0.0
    assert len(per_poll_ok) >= 10 and served >= 0.9, (len(per_poll_ok), per_poll_ok.count(False))
    assert rejected(gw, "max_per_source") == 0


@pytest.mark.parametrize(
    "when_full", ["close_oldest_idle", pytest.param("refuse", marks=pytest.mark.slow)]
)
def test_silent_connections_from_many_addresses_close_none_of_a_busy_hosts_masters(
    gateway_with: GatewayOnSim, when_full: str
) -> None:
    _sim, gw = gateway_with(
        {1: plc(1)}, line=HONEST_LINE, server={"max_connections": 20, "when_full": when_full}
    )
    scada_host = OTHER
    silent_hosts = [f"127.0.0.{10 + n}" for n in range(22)]
    stop = threading.Event()
    polls: list[bool] = []
    lost: list[int] = []  # SCADA connections the gateway closed, by index

    def scada_master(index: int) -> None:
        """Polls every 0.3 s on one kept connection; reconnects when it is closed."""
        client: ClientFrom | None = None
        while not stop.is_set():
            try:
                if client is None:
                    client = ClientFrom(scada_host, gw.address)
                polls.append(client.request(1, READ_1)[0] == 0x03)
            except (OSError, AssertionError):
                polls.append(False)
                lost.append(index)
                if client is not None:
                    client.close()
                client = None
            stop.wait(0.3)  # the SCADA's poll period, not a synchronisation
        if client is not None:
            client.close()

    masters = [threading.Thread(target=scada_master, args=(n,), daemon=True) for n in range(3)]
    held: dict[str, socket.socket] = {}
    try:
        for master in masters:
            master.start()
        wait_until(lambda: len(polls) >= 3, "the SCADA host's first polls")
        # Each silent host keeps one connection open, and opens it again whenever the
        # gateway closes it, for 2.5 s (bounded: at most 30 rounds of 22 connections).
        deadline = time.monotonic() + 2.5
        for _ in range(30):
            if time.monotonic() >= deadline:
                break
            for host in silent_hosts:
                sock = held.get(host)
                if sock is None or _closed_by_peer(sock):
                    if sock is not None:
                        sock.close()
                    with suppress(OSError):
                        held[host] = connect_from(host, gw.address)
            stop.wait(0.1)  # the attacker's round, not a synchronisation
    finally:
        stop.set()
        for master in masters:
            master.join(DEADLINE_S)
        for sock in held.values():
            sock.close()
    assert len(polls) >= 20
    assert lost == [], f"SCADA connections closed: {len(lost)} of {len(polls)} polls failed"
    assert sum(polls) / len(polls) >= 0.95, polls.count(False)
    assert rejected(gw, "max_connections") + evicted(gw) >= 2  # the silent hosts were turned away
