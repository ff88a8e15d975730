"""The pair's network channel over real loopback: ``GET /role`` polled with the endpoint's
token, over HTTPS with a test PKI; every failure is *unreachable*, never a role."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import ssl
from collections.abc import Mapping
from pathlib import Path

import pytest
from prometheus_client import CollectorRegistry

from gateway.config import MetricsConfig, build_config
from gateway.core.line import LineRequest
from gateway.core.outcome import Outcome
from gateway.core.redundancy import Role
from gateway.io.http.endpoint import HttpEndpoint, respond, start_http
from gateway.io.http.guard import RouteAccess
from gateway.io.pair.channel import (
    PeerPoller,
    PeerRole,
    parse_role,
    peer_tls,
    role_body,
    split_answer,
)
from gateway.io.pair.role import boot_time
from gateway.sim import plc
from gateway.sim.pki import Pki, make_pki
from tests.helpers import GatewayFactory, SimFactory, wait_until

READ_1 = bytes.fromhex("0300000001")

TOKEN = "a-long-random-pair-token"
DEADLINE_S = 5.0


async def role_route(
    method: str, _target: str, _headers: Mapping[str, str],
    _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
) -> None:  # fmt: skip
    await respond(writer, 503, "application/json", role_body(Role.STANDBY, 0.0, 7, True), method)


async def endpoint(config: MetricsConfig) -> HttpEndpoint:
    routes = {"/role": (role_route, RouteAccess.STATUS)}
    return await start_http(config, CollectorRegistry(), lambda: (True, "ok"), routes)


async def poll_once(
    address: tuple[str, int], token: str | None = TOKEN, tls: ssl.SSLContext | None = None
) -> PeerRole | str:
    """What one round of a poller hands on: the role, or why the peer is unreachable."""
    found: asyncio.Future[PeerRole | str] = asyncio.get_running_loop().create_future()

    def settle(result: PeerRole | str) -> None:
        if not found.done():
            found.set_result(result)

    poller = PeerPoller(address, interval=0.05, timeout=1.0, on_role=settle,
                        on_unreachable=settle, token=token, tls=tls)  # fmt: skip
    poller.start()
    try:
        return await asyncio.wait_for(found, DEADLINE_S)
    finally:
        await poller.stop()


def https_endpoint(pki: Pki, host: str) -> MetricsConfig:
    """An HTTPS endpoint on ``host`` with the test PKI's server certificate (it names
    127.0.0.1 and localhost) and the pair's token."""
    return MetricsConfig(True, host, 0, status_token=TOKEN,
                         tls_cert=str(pki.server_chain), tls_key=str(pki.server_key))  # fmt: skip


def test_the_role_comes_over_https_with_the_token(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    config = https_endpoint(pki, "127.0.0.1")

    async def scenario() -> None:
        served = await endpoint(config)
        try:
            tls = peer_tls(str(pki.server_chain), str(pki.server_key), str(pki.ca))
            got = await poll_once(served.address, tls=tls)
            assert got == PeerRole(Role.STANDBY, 0.0, 7)
            # Without the token the endpoint refuses: the peer is unreachable, not standby.
            refused = await poll_once(served.address, token=None, tls=tls)
            assert refused == "ValueError: HTTP 401"
            # A peer whose certificate the pair's CA did not sign is not believed.
            untrusted = peer_tls(str(pki.server_chain), str(pki.server_key), None)
            assert "SSL" in str(await poll_once(served.address, tls=untrusted))
        finally:
            await served.close()

    asyncio.run(scenario())


def test_a_peer_whose_certificate_does_not_name_its_address_is_not_believed(
    tmp_path: Path,
) -> None:
    """The same CA's certificate, for 127.0.0.1 and localhost, served at 127.0.0.2: not the
    peer (any other device of the plant's CA could otherwise claim to be active)."""
    pki = make_pki(tmp_path)

    async def poll_elsewhere() -> str:
        served = await endpoint(https_endpoint(pki, "127.0.0.2"))
        tls = peer_tls(str(pki.server_chain), str(pki.server_key), str(pki.ca))
        try:
            return str(await poll_once(served.address, tls=tls))
        finally:
            await served.close()

    why = asyncio.run(poll_elsewhere())
    assert "SSLCertVerificationError" in why and "127.0.0.2" in why, why


def test_no_listener_and_a_stranger_are_unreachable() -> None:
    async def scenario() -> None:
        with socket.socket() as hole:  # a port nobody listens on
            hole.bind(("127.0.0.1", 0))
            address = hole.getsockname()[:2]
        assert "ConnectionRefused" in str(await poll_once(address))

        async def stranger(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}")
            await writer.drain()
            writer.close()

        server = await asyncio.start_server(stranger, "127.0.0.1", 0)
        try:
            got = await poll_once(server.sockets[0].getsockname()[:2])
            assert str(got).startswith("KeyError")  # a JSON object, but no role in it
        finally:
            server.close()
            await server.wait_closed()

    asyncio.run(scenario())


@pytest.mark.parametrize(
    ("status", "body"),
    [
        (404, b'{"role": "active", "lease_remaining": 1, "priority": 1}'),
        (200, b'{"role": "leader", "lease_remaining": 1, "priority": 1}'),
        (200, b'{"role": "active", "lease_remaining": -1, "priority": 1}'),
        (200, b'{"role": "active", "lease_remaining": true, "priority": 1}'),
        (200, b'{"role": "active", "lease_remaining": 1, "priority": "high"}'),
        (200, b"[1, 2]"),
        (200, b"not json"),
    ],
)
def test_anything_but_a_role_document_is_refused(status: int, body: bytes) -> None:
    with pytest.raises((ValueError, KeyError)):
        parse_role(status, body)


def test_an_answer_without_the_end_of_its_head_is_refused() -> None:
    with pytest.raises(ValueError):
        split_answer(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n")
    assert split_answer(b"HTTP/1.1 503 Service Unavailable\r\nA: b\r\n\r\n{}") == (
        503, {"a": "b"}, b"{}",
    )  # fmt: skip


def test_the_role_document_carries_both_leases() -> None:
    body = role_body(Role.ACTIVE, 1.0, 5, True, 0.7509)
    assert parse_role(200, body) == PeerRole(Role.ACTIVE, 1.0, 5, 0.75)  # rounded down
    older = b'{"role": "standby", "lease_remaining": 0, "priority": 5}'  # no acknowledgement
    assert parse_role(503, older) == PeerRole(Role.STANDBY, 0.0, 5, 0.0)


def test_a_reload_keeps_the_pair_settings_it_started_with(
    make_sim: SimFactory, make_gateway: GatewayFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Pairing, or changing a pair, needs a restart: a reload warns and keeps what runs."""
    sim = make_sim({1: plc(1)})
    raw = {"lines": {"a": {"device": sim.path, "units": [1]}}}
    gateway = make_gateway(raw)
    paired = {**raw, "redundancy": {"peer": "127.0.0.1:1", "peer_modbus": "127.0.0.1:2"}}
    with caplog.at_level(logging.WARNING, logger="gateway"):
        gateway.run(gateway.gateway.reload(build_config(paired, "<test>")))
    assert "[redundancy] changes need a restart" in caplog.text
    assert not gateway.call(lambda: gateway.gateway.config.redundancy.paired)
    assert gateway.call(lambda: gateway.gateway.pair) is None


def test_a_frame_the_lease_check_refuses_is_answered_0x0a_at_once(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """The lease lapses between the line's choice of a frame and its write (the loop was
    held past the lease, as by a VM pause): the frame is not written; its request is
    answered 0x0A at once, not 0x0B after its timeout, without a miss counted against its
    slave; the gateway steps down."""
    sim = make_sim({1: plc(1)})
    with socket.socket() as hole:  # a peer nobody answers for: this gateway takes over
        hole.bind(("127.0.0.1", 0))
        nobody = f"127.0.0.1:{hole.getsockname()[1]}"
    lease = 0.2
    gateway = make_gateway({
        "lines": {"a": {**sim.line_table([1]), "timeout": 1.0}},
        "redundancy": {"peer": nobody, "peer_modbus": nobody, "lease": lease,
                       "takeover_after": 0.6, "keepalive": "off"},
    })  # fmt: skip
    running = gateway.gateway
    pair = running.pair
    assert pair is not None
    wait_until(lambda: gateway.call(lambda: not pair.standing_by), "the gateway active")
    answers: list[tuple[bytes, Outcome]] = []

    def held_past_the_lease_then_asked() -> tuple[bool, int]:
        bus = running.buses["a"]
        held_until = boot_time() + 1.5 * lease
        while boot_time() < held_until:  # the loop held: no tick renews the lease
            pass
        bus.submit(LineRequest(1, READ_1, "m", lambda pdu, outcome: answers.append((pdu, outcome))))
        record = bus._core.health.slaves.get(1)
        return bus.refused, 0 if record is None else record.misses

    refused, misses = gateway.call(held_past_the_lease_then_asked)
    assert refused
    assert answers == [(bytes((0x83, 0x0A)), Outcome.NO_ROUTE)]  # within the same call
    assert misses == 0
    wait_until(lambda: gateway.call(lambda: pair.standing_by), "the gateway standing by")


def test_a_gateway_alone_answers_its_role_active_and_unpaired(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """keepalived's check script follows a gateway alone too: 200, active, not paired."""
    sim = make_sim({1: plc(1)})
    gateway = make_gateway({"lines": {"a": {"device": sim.path, "units": [1]}}})
    address = gateway.gateway.metrics_address
    assert address is not None

    async def ask() -> tuple[int, bytes]:
        reader, writer = await asyncio.open_connection(*address)
        host = f"{address[0]}:{address[1]}"
        writer.write(f"GET /role HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode())
        answer = await asyncio.wait_for(reader.read(), DEADLINE_S)
        writer.close()
        status, _headers, body = split_answer(answer)
        return status, body

    status, body = asyncio.run(ask())
    assert status == 200
    assert parse_role(status, body) == PeerRole(Role.ACTIVE, 0.0, 100)
    assert json.loads(body)["paired"] is False
