"""``max_in_flight``: several requests outstanding on one Modbus TCP slave connection.

libmodbus's Modbus TCP server (through ctypes) behind a ``kind = "tcp"`` line with
``max_in_flight = 4``, several masters pipelining, every answer checked, read-after-write
kept per master. pymodbus 3.16's ``ModbusTcpServer`` serves one request per read of its
socket (requests arriving together are lost): a device that accepts only one, which the
default (1) serves with the same traffic. A slave of our own that holds requests and
answers them in reverse order shows how many were outstanding at once and that answers
are matched by transaction id; with the default it never sees a second request before
it answered the first. When it hangs up with four outstanding, each gets 0x0A once. The
simulator's own Modbus TCP slave, with one unit answering late, has answers overtake each
other on the connection.
"""

from __future__ import annotations

import ctypes
import os
import socket
import struct
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from gateway.sim import SimulatedTcpSlave
from gateway.sim.device import pack_registers
from gateway.sim.profiles import plc
from tests.helpers import DEADLINE_S, GatewayFactory, RawClient, mbap, read
from tests.integration.metrics_harness import samples, series
from tests.integration.test_tcp_slaves import PymodbusTcpSlave, tcp_slave, wait_up

__all__ = ["tcp_slave"]  # the fixture, imported for the tests below


class LibmodbusTcpSlave:
    """libmodbus's Modbus TCP server in a thread: 64 holding registers, register i = 10 x i.

    ``modbus_receive`` reads exactly one ADU per call, so pipelined requests are served
    one after the other, in order, from the socket's buffer.
    """

    class Mapping(ctypes.Structure):
        _fields_ = [
            *[(name, ctypes.c_int) for name in (
                "nb_bits", "start_bits", "nb_input_bits", "start_input_bits",
                "nb_input_registers", "start_input_registers", "nb_registers",
                "start_registers")],
            ("tab_bits", ctypes.POINTER(ctypes.c_uint8)),
            ("tab_input_bits", ctypes.POINTER(ctypes.c_uint8)),
            ("tab_input_registers", ctypes.POINTER(ctypes.c_uint16)),
            ("tab_registers", ctypes.POINTER(ctypes.c_uint16)),
        ]  # fmt: skip

    def __init__(self) -> None:
        try:
            lib: Any = ctypes.CDLL("libmodbus.so.5")
        except OSError as error:
            reason = f"libmodbus (apt package libmodbus5) is missing: {error}"
            if os.environ.get("CI"):
                pytest.fail(f"{reason}; CI must run this test")
            pytest.skip(reason)
        lib.modbus_new_tcp.restype = ctypes.c_void_p
        lib.modbus_new_tcp.argtypes = [ctypes.c_char_p, ctypes.c_int]
        lib.modbus_tcp_listen.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.modbus_tcp_accept.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int)]
        lib.modbus_mapping_new.restype = ctypes.POINTER(self.Mapping)
        lib.modbus_receive.argtypes = [ctypes.c_void_p, ctypes.c_char_p]
        lib.modbus_reply.argtypes = [
            ctypes.c_void_p, ctypes.c_char_p, ctypes.c_int, ctypes.POINTER(self.Mapping),
        ]  # fmt: skip
        lib.modbus_close.argtypes = lib.modbus_free.argtypes = [ctypes.c_void_p]
        self.lib = lib
        self.ctx = lib.modbus_new_tcp(b"127.0.0.1", 0)
        self.mapping = lib.modbus_mapping_new(0, 0, 64, 0)
        for index in range(64):
            self.mapping.contents.tab_registers[index] = 10 * index
        self.listen_fd = lib.modbus_tcp_listen(self.ctx, 1)
        assert self.listen_fd >= 0, "libmodbus could not listen"
        probe = socket.socket(fileno=os.dup(self.listen_fd))
        self.port: int = probe.getsockname()[1]
        probe.close()
        self.served = 0
        self._thread = threading.Thread(target=self._serve, name="libmodbus-tcp", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        lib = self.lib
        fd = ctypes.c_int(self.listen_fd)
        if lib.modbus_tcp_accept(self.ctx, ctypes.byref(fd)) < 0:
            return
        query = ctypes.create_string_buffer(260)
        while (length := lib.modbus_receive(self.ctx, query)) != -1:
            if length > 0:
                lib.modbus_reply(self.ctx, query, length, self.mapping)
                self.served += 1

    def close(self) -> None:
        os.close(self.listen_fd)
        self._thread.join(DEADLINE_S)  # the gateway closed its connection: receive failed
        self.lib.modbus_close(self.ctx)
        self.lib.modbus_free(self.ctx)


def pipeline_writes_and_reads(masters: list[RawClient], unit: int, rounds: int) -> None:
    """Each master writes its own register, reads it back at once (not waiting for the
    write's answer), and reads registers nobody writes; every answer is checked."""
    for round_ in range(rounds):
        expected: list[list[tuple[int, bytes]]] = []
        for number, client in enumerate(masters):
            value = 1000 * number + round_
            change = struct.pack(">BHH", 6, number, value)
            sent = [(client.send(unit, change), change)]
            sent.append((client.send(unit, read(number)), h3(pack_registers([value]))))
            for address in range(8 + number, 18 + number, 3):
                registers = pack_registers([10 * a for a in range(address, address + 3)])
                sent.append((client.send(unit, read(address, 3)), h3(registers)))
            expected.append(sent)
        for client, sent in zip(masters, expected, strict=True):
            for tid, pdu in sent:
                reply = client.receive()
                assert (reply.transaction_id, reply.unit, reply.pdu) == (tid, unit, pdu)


def test_masters_pipeline_through_four_in_flight_to_libmodbus(
    make_gateway: GatewayFactory,
) -> None:
    slave = LibmodbusTcpSlave()
    table = {"kind": "tcp", "address": f"127.0.0.1:{slave.port}", "units": [7],
             "max_in_flight": 4, "max_queue_per_master": 64}  # fmt: skip
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    masters = [gw.connect() for _ in range(6)]
    try:
        pipeline_writes_and_reads(masters, 7, 5)
        found = samples(gw)
        for reason in ("late", "unexpected_tid"):
            key = series("modbus_gateway_discarded_frames_total", line="plc", reason=reason)
            assert found[key] == 0
    finally:
        for client in masters:
            client.close()
        gw.stop()  # closes the slave's connection: its thread ends
        slave.close()
    assert slave.served == 6 * 5 * 6


def test_a_slave_that_takes_one_request_at_a_time_is_served_by_default(
    tcp_slave: PymodbusTcpSlave, make_gateway: GatewayFactory
) -> None:
    table = {"kind": "tcp", "address": f"127.0.0.1:{tcp_slave.port}", "units": [7],
             "max_queue_per_master": 64}  # fmt: skip
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    masters = [gw.connect() for _ in range(6)]
    try:
        pipeline_writes_and_reads(masters, 7, 3)
    finally:
        for client in masters:
            client.close()


def h3(registers: bytes) -> bytes:
    return bytes((3, len(registers))) + registers


class ReorderingSlave:
    """A Modbus TCP slave that collects up to ``hold`` requests, then answers them last
    first (FC 3: every register holds its own address). It counts how many requests it
    had received and not yet answered at most. With ``drop_first``, its first connection
    is closed, unanswered, once ``hold`` requests are outstanding on it."""

    def __init__(self, hold: int, drop_first: bool = False) -> None:
        self.hold = hold
        self.drop_first = drop_first
        self.most_outstanding = 0
        self.connections = 0
        self.dropped = 0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.05)  # to see ``close`` between connections
        self.port = self.listener.getsockname()[1]
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._closing.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            self.connections += 1
            with conn:
                self._session(conn, drop=self.drop_first and self.connections == 1)

    def _session(self, conn: socket.socket, drop: bool) -> None:
        buffer = b""
        held: list[tuple[int, int, bytes]] = []
        conn.settimeout(0.2)
        while True:
            try:
                data = conn.recv(4096)
            except TimeoutError:
                data = None  # quiet: answer what is held
            if data == b"" or (data is None and self._closing.is_set()):
                return
            if data:
                buffer += data
                while len(buffer) >= 7 and len(buffer) >= 6 + buffer[5]:
                    end = 6 + buffer[5]
                    tid = struct.unpack(">H", buffer[:2])[0]
                    held.append((tid, buffer[6], buffer[7:end]))
                    buffer = buffer[end:]
                self.most_outstanding = max(self.most_outstanding, len(held))
            if drop and len(held) >= self.hold:
                self.dropped = len(held)
                return  # the connection closes with every request unanswered
            if held and (data is None or len(held) >= self.hold):
                for tid, unit, pdu in reversed(held):
                    address, quantity = struct.unpack(">HH", pdu[1:5])
                    answer = h3(pack_registers(list(range(address, address + quantity))))
                    conn.sendall(mbap(tid, unit, answer))
                held.clear()

    def close(self) -> None:
        self._closing.set()
        self._thread.join(DEADLINE_S)
        self.listener.close()


@pytest.fixture
def reordering_slave(request: pytest.FixtureRequest) -> Iterator[ReorderingSlave]:
    slave = ReorderingSlave(request.param)
    yield slave
    slave.close()


@pytest.fixture
def dropping_slave() -> Iterator[ReorderingSlave]:
    slave = ReorderingSlave(4, drop_first=True)
    yield slave
    slave.close()


def poll_everyone(masters: list[RawClient], rounds: int) -> None:
    """Each master sends its reads at once, then checks every answer is its own."""
    for round_ in range(rounds):
        sent = []
        for number, client in enumerate(masters):
            address = 100 * number + round_
            sent.append((client, client.send(9, read(address, 2)), address))
        for client, tid, address in sent:
            reply = client.receive()
            assert (reply.transaction_id, reply.pdu) == (
                tid, h3(pack_registers([address, address + 1])),
            )  # fmt: skip


@pytest.mark.parametrize("reordering_slave", [4], indirect=True)
def test_four_outstanding_answered_last_first_each_reach_their_master(
    reordering_slave: ReorderingSlave, make_gateway: GatewayFactory
) -> None:
    table = {"kind": "tcp", "address": f"127.0.0.1:{reordering_slave.port}", "units": [9],
             "max_in_flight": 4, "timeout": 5}  # fmt: skip
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    masters = [gw.connect() for _ in range(4)]
    try:
        poll_everyone(masters, 10)
    finally:
        for client in masters:
            client.close()
    assert reordering_slave.most_outstanding == 4


@pytest.mark.parametrize("reordering_slave", [1], indirect=True)
def test_by_default_a_slave_never_has_two_requests_outstanding(
    reordering_slave: ReorderingSlave, make_gateway: GatewayFactory
) -> None:
    table = {"kind": "tcp", "address": f"127.0.0.1:{reordering_slave.port}", "units": [9]}
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    masters = [gw.connect() for _ in range(4)]
    try:
        poll_everyone(masters, 5)
    finally:
        for client in masters:
            client.close()
    assert reordering_slave.most_outstanding == 1


def test_a_lost_connection_answers_every_outstanding_request_once(
    dropping_slave: ReorderingSlave, make_gateway: GatewayFactory
) -> None:
    table = {"kind": "tcp", "address": f"127.0.0.1:{dropping_slave.port}", "units": [9],
             "max_in_flight": 4, "timeout": 5}  # fmt: skip
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    masters = [gw.connect() for _ in range(4)]
    try:
        sent = [(client, client.send(9, read(100 * n, 2))) for n, client in enumerate(masters)]
        for client, tid in sent:  # the four outstanding when the slave hung up: 0x0A each
            reply = client.receive()
            assert (reply.transaction_id, reply.pdu) == (tid, bytes((0x83, 0x0A)))
        wait_up(gw)  # reconnected
        poll_everyone(masters, 3)  # a second answer to any of the four would show up here
    finally:
        for client in masters:
            client.close()
    assert (dropping_slave.connections, dropping_slave.dropped) == (2, 4)


def test_the_simulators_tcp_slave_with_a_slow_unit_behind_four_in_flight(
    make_gateway: GatewayFactory,
) -> None:
    """Unit 1 answers 20 ms late, unit 2 at once: answers overtake each other on the
    connection; each master's write is read back right behind it, every answer checked."""
    with SimulatedTcpSlave({1: plc(1), 2: plc(2)}) as slave:
        slave.faults(1).reply_delay = 0.02
        table = {"kind": "tcp", "address": slave.host_port, "units": [1, 2],
                 "max_in_flight": 4, "timeout": 2, "max_queue_per_master": 64}  # fmt: skip
        gw = make_gateway({"lines": {"plc": table}})
        wait_up(gw)
        masters = [gw.connect() for _ in range(6)]
        try:
            for round_ in range(4):
                expected: list[dict[int, tuple[int, bytes]]] = []
                for number, client in enumerate(masters):
                    unit, other = 1 + number % 2, 2 - number % 2
                    value = 100 * number + round_
                    change = struct.pack(">BHH", 6, 100 + number, value)
                    address = 1000 + 10 * number + round_
                    mine = {
                        client.send(unit, change): (unit, change),
                        client.send(unit, read(100 + number)): (unit, h3(pack_registers([value]))),
                        client.send(other, read(address, 4)): (
                            other, h3(pack_registers(list(range(address, address + 4)))),
                        ),
                    }  # fmt: skip
                    expected.append(mine)
                for client, mine in zip(masters, expected, strict=True):
                    replies = [client.receive() for _ in mine]
                    assert {r.transaction_id: (r.unit, r.pdu) for r in replies} == mine
        finally:
            for client in masters:
                client.close()
        stats = slave.stats()
        assert 2 <= stats.max_in_flight <= 4, stats
        assert stats.requests == stats.responses == 6 * 4 * 3
