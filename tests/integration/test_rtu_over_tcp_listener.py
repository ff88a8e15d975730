"""The ``rtu-over-tcp`` listener: masters sending bare RTU frames over TCP to the gateway.

A raw socket client checks the bytes (framing by length and CRC whatever the
segments, answers in order, silence for broadcasts, a bad CRC closing the
connection), and pymodbus's TCP client with its RTU framer is the independent
master. Policies and allow lists apply as on every listener.
"""

from __future__ import annotations

import socket
import time
from typing import Any

import pytest

from gateway.config import build_config
from gateway.core.crc import append_crc, check_crc
from gateway.sim import plc, zl69x
from gateway.sim.device import pack_registers
from tests.helpers import DEADLINE_S, GatewayFactory, RunningGateway, SimBus, SimFactory, h
from tests.integration.test_sim import FUNCTION_VECTORS


def listener_address(gateway: RunningGateway, name: str = "rtu") -> tuple[str, int]:
    server = next(s for s in gateway.gateway.servers if s.name == name)
    host, port = server.sockets[0]
    return host, port


class RtuClient:
    """A master writing RTU frames on a TCP socket and reading whole RTU replies back."""

    def __init__(self, address: tuple[str, int], source: str | None = None) -> None:
        self.sock = socket.socket()
        if source is not None:
            self.sock.bind((source, 0))
        self.sock.settimeout(DEADLINE_S)
        self.sock.connect(address)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def close(self) -> None:
        self.sock.close()

    def send(self, unit: int, pdu: bytes) -> None:
        self.sock.sendall(append_crc(bytes((unit,)) + pdu))

    def receive(self, length: int, timeout: float = DEADLINE_S) -> bytes:
        """Exactly ``length`` bytes (a whole reply), CRC checked; returns unit + PDU."""
        self.sock.settimeout(timeout)
        data = b""
        while len(data) < length:
            chunk = self.sock.recv(length - len(data))
            assert chunk, f"closed after {data.hex(' ')}"
            data += chunk
        assert check_crc(data), data.hex(" ")
        return data[:-2]

    def request(self, unit: int, pdu: bytes, reply_pdu_length: int) -> bytes:
        self.send(unit, pdu)
        reply = self.receive(reply_pdu_length + 3)
        assert reply[0] == unit
        return reply[1:]

    def closed_by_peer(self, timeout: float = DEADLINE_S) -> bool:
        self.sock.settimeout(timeout)
        try:
            return self.sock.recv(1) == b""
        except ConnectionResetError:
            return True


Start = Any  # start(listener=None, policies=None, devices=None) -> (SimBus, RunningGateway)


@pytest.fixture
def start(make_sim: SimFactory, make_gateway: GatewayFactory) -> Start:
    """A simulated PLC (1) and ZL-69X (2), or ``devices``; listeners ``tcp`` and ``rtu``
    (rtu-over-tcp)."""

    def factory(
        listener: dict[str, Any] | None = None,
        policies: dict[str, Any] | None = None,
        devices: dict[int, Any] | None = None,
    ) -> tuple[SimBus, RunningGateway]:
        devices = devices if devices is not None else {1: plc(1), 2: zl69x(2)}
        sim = make_sim(devices)
        entry = {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0"}
        entry.update(listener or {})
        raw: dict[str, Any] = {
            "lines": {"a": sim.line_table(sorted(devices))},
            "listeners": [entry],
        }
        if policies:
            raw["policies"] = policies
        return sim, make_gateway(raw)

    return factory


def test_reads_and_writes_over_rtu_frames(start: Start) -> None:
    sim, gateway = start()
    client = RtuClient(listener_address(gateway))
    try:
        # The specification's read of holding registers, answered as an RTU frame.
        assert client.request(1, h("03 0000 000A"), 22) == h("03 14") + pack_registers(
            [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
        )
        assert client.request(1, h("10 0BB8 0002 04 1234 5678"), 5) == h("10 0BB8 0002")
        assert sim.device(1).holding.read(3000, 2) == [0x1234, 0x5678]
        assert client.request(2, h("03 0000 0002"), 6) == h("03 04 0113 FF9D")
        assert client.request(1, h("08 0000 A537"), 5) == h("08 0000 A537")
        assert client.request(9, h("03 0000 0001"), 2) == h("83 0A")  # no route
        assert client.request(1, h("03 FFFF 0002"), 2) == h("83 02")  # the device's exception
    finally:
        client.close()
    # The tcp listener is still there beside it.
    with gateway.connect() as tcp:
        assert tcp.request(1, h("03 0BB8 0002")) == h("03 04 1234 5678")


def test_requests_cut_anywhere_and_sent_back_to_back_are_answered_in_order(
    start: Start,
) -> None:
    sim, gateway = start()
    client = RtuClient(listener_address(gateway))
    requests = [(1, 1000 + 7 * i, 1 + i % 9) for i in range(12)]
    requests += [(2, 0, 2), (1, 2000, 3), (2, 8, 1)]
    stream = b"".join(
        append_crc(bytes((unit,)) + h("03") + a.to_bytes(2, "big") + q.to_bytes(2, "big"))
        for unit, a, q in requests
    )
    try:
        for start_ in range(0, len(stream), 5):  # segments of 5 bytes, across frame boundaries
            client.sock.sendall(stream[start_ : start_ + 5])
        for unit, address, quantity in requests:
            reply = client.receive(3 + 2 + 2 * quantity)
            table = sim.device(unit).holding.read(address, quantity)
            assert reply == bytes((unit, 3, 2 * quantity)) + pack_registers(table)
    finally:
        client.close()


def test_one_request_at_a_time_also_after_a_reload_asks_for_pipelining(start: Start) -> None:
    """RTU has no transaction id: the answers must come in the order of the requests. A
    request answered locally (no route) behind one that waits for the line would overtake
    it if the connection read both at once; ``[server] max_pipeline`` never applies here,
    not even after a reload sets it."""
    sim, gateway = start()

    def in_order(client: RtuClient) -> None:
        stream = append_crc(h("01 03 0000 0002")) + append_crc(h("09 03 0000 0001"))
        client.sock.sendall(stream)  # back to back, in one segment
        assert client.receive(3 + 2 + 4) == h("01 03 04") + pack_registers([0, 2])
        assert client.receive(3 + 2) == h("09 83 0A")

    client = RtuClient(listener_address(gateway))
    try:
        in_order(client)
        tables = {
            "server": {"max_pipeline": 16},
            "lines": {"a": sim.line_table([1, 2])},
            "listeners": [{"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0"}],
        }
        gateway.run(gateway.gateway.reload(build_config(tables, "<reload>")))
        in_order(client)
    finally:
        client.close()


def test_a_broadcast_is_executed_and_never_answered(start: Start) -> None:
    sim, gateway = start()
    client = RtuClient(listener_address(gateway))
    try:
        client.send(0, h("06 0005 0BCD"))
        # The next request's answer is the first thing that comes back.
        assert client.request(1, h("03 0005 0001"), 4) == h("03 02 0BCD")
        assert sim.stats().broadcasts == 1
    finally:
        client.close()


@pytest.mark.parametrize(
    ("sent_hex", "kind"),
    [
        ("01 03 0000 0001 0000", "bad_crc"),
        # No length to predict, no end in sight.
        ("01 41" + " 00" * 300, "too_long"),
    ],
    ids=["a bad CRC", "an endless request of unknown length"],
)
def test_a_frame_that_cannot_be_served_closes_the_connection_and_is_counted(
    start: Start, sent_hex: str, kind: str
) -> None:
    _, gateway = start()
    client = RtuClient(listener_address(gateway))
    try:
        client.sock.sendall(h(sent_hex))
        assert client.closed_by_peer()
    finally:
        client.close()
    registry = gateway.gateway.metrics.registry
    count = gateway.call(
        lambda: registry.get_sample_value("modbus_gateway_protocol_errors_total", {"kind": kind})
    )
    assert count == 1


def test_a_user_function_of_unknown_length_ends_on_silence(start: Start) -> None:
    _, gateway = start()
    client = RtuClient(listener_address(gateway))
    try:
        sent = time.monotonic()
        client.send(1, h("41 0102 0304"))  # the PLC does not know it: exception 0x01
        assert client.receive(5) == h("01 C1 01")
        assert time.monotonic() - sent >= 0.05  # it waited for the silence that ends it
    finally:
        client.close()


def test_policies_and_allow_lists_apply(start: Start) -> None:
    policies = {"readers": {"rules": [{"source": "127.0.0.1", "units": "1-2", "access": "read"}]}}
    _, gateway = start({"policy": "readers", "allow": ["127.0.0.1", "127.0.0.2"]}, policies)
    reader = RtuClient(listener_address(gateway))
    try:
        assert client_read(reader) == h("03 02 0000")
        assert reader.request(1, h("06 0000 0001"), 2) == h("86 01")  # writes are not granted
    finally:
        reader.close()
    other = RtuClient(listener_address(gateway), source="127.0.0.2")  # allowed in, no rule
    try:
        assert other.request(1, h("03 0000 0001"), 2) == h("83 01")
    finally:
        other.close()
    stranger = RtuClient(listener_address(gateway), source="127.0.0.3")  # not on the allow list
    try:
        assert stranger.closed_by_peer()
    finally:
        stranger.close()


def client_read(client: RtuClient) -> bytes:
    return client.request(1, h("03 0000 0001"), 4)


def test_pymodbus_master_with_the_rtu_framer_over_tcp(start: Start) -> None:
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient

    sim, gateway = start()
    host, port = listener_address(gateway)
    client: Any = ModbusTcpClient(host, port=port, framer=FramerType.RTU, timeout=5, retries=0)
    assert client.connect()
    try:
        assert client.read_holding_registers(1000, count=5, device_id=1).registers == [
            1000, 1001, 1002, 1003, 1004,
        ]  # fmt: skip
        assert not client.write_registers(3000, [7, 8, 9], device_id=1).isError()
        assert sim.device(1).holding.read(3000, 3) == [7, 8, 9]
        assert not client.write_coil(0xAC, True, device_id=1).isError()
        assert client.read_coils(0xAC, count=1, device_id=1).bits[0] is True
        assert client.read_holding_registers(0, count=2, device_id=2).registers == [0x0113, 0xFF9D]
        assert client.read_holding_registers(0xFFFF, count=2, device_id=1).isError()
    finally:
        client.close()


@pytest.mark.parametrize(("request_hex", "response_hex"), FUNCTION_VECTORS)
def test_every_function_code_through_the_listener(
    start: Start, request_hex: str, response_hex: str
) -> None:
    """The simulator's vectors, sent as RTU frames over TCP: the same answers, byte for byte."""
    _, gw = start(devices={7: plc(7)})
    client = RtuClient(listener_address(gw))
    try:
        assert client.request(7, h(request_hex), len(h(response_hex))) == h(response_hex)
    finally:
        client.close()
