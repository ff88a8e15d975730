"""``kind = "rtu-over-tcp"`` lines: RTU frames over TCP to a serial device server.

The device servers are real: socat (``TCP-LISTEN`` in front of the simulated
line's pty, as a Moxa NPort in raw socket mode), a small Python bridge that
cuts every answer into TCP segments of a few bytes, and pymodbus's TCP server
with its RTU framer as an independent peer. Every function code goes through
the network line and is compared with what the same requests get from a serial
line in front of an identical device.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import signal
import socket
import subprocess
import threading
import time
import tty
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest

from gateway.core.crc import append_crc
from gateway.sim import plc, zl69x
from gateway.sim.device import pack_registers
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimBus,
    SimFactory,
    h,
    require_tool,
    wait_until,
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def line_table(address: str, units: list[int], **options: Any) -> dict[str, Any]:
    table: dict[str, Any] = {"kind": "rtu-over-tcp", "address": address, "units": units,
                             "baudrate": 115200, "timeout": 0.5}  # fmt: skip
    table.update(options)
    return table


# --------------------------------------------------------------------------- device servers


class Socat:
    """socat as a serial device server: one TCP connection at a time, bridged to a pty."""

    def __init__(self, port: int, path: str) -> None:
        self.port = port
        self.path = path
        self.process: subprocess.Popen[bytes] | None = None
        self._drainer: threading.Thread | None = None

    def start(self) -> None:
        socat = require_tool("socat")
        self.process = subprocess.Popen(
            [socat, "-d", "-d", f"TCP-LISTEN:{self.port},bind=127.0.0.1,reuseaddr,fork",
             f"FILE:{self.path},raw,echo=0"],
            stderr=subprocess.PIPE,
        )  # fmt: skip
        assert self.process.stderr is not None
        deadline = time.monotonic() + DEADLINE_S
        seen = b""
        while b"listening on" not in seen:
            readable, _, _ = select.select([self.process.stderr], [], [], 0.5)
            assert time.monotonic() < deadline, f"socat did not listen: {seen!r}"
            if readable:
                chunk = os.read(self.process.stderr.fileno(), 4096)
                assert chunk, f"socat exited: {seen!r}"
                seen += chunk
        self._drainer = threading.Thread(target=self._drain, args=(self.process,), daemon=True)
        self._drainer.start()

    @staticmethod
    def _drain(process: subprocess.Popen[bytes]) -> None:
        assert process.stderr is not None
        while process.stderr.read(4096):
            pass

    def kill(self) -> None:
        """Kill the whole device server (SIGKILL: no goodbye on the connection but the FIN)."""
        if self.process is not None and self.process.poll() is None:
            # socat forks a child per connection, which outlives its parent: kill both.
            children = _children(self.process.pid)
            self.process.kill()
            for child in children:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(child, signal.SIGKILL)
            self.process.wait(DEADLINE_S)
        # The drainer ends at the pipe's end of file; then the pipe can be closed.
        if self._drainer is not None and self.process is not None:
            self._drainer.join(DEADLINE_S)
            if not self._drainer.is_alive() and self.process.stderr is not None:
                self.process.stderr.close()


def _children(pid: int) -> list[int]:
    children: list[int] = []
    try:
        with open(f"/proc/{pid}/task/{pid}/children", encoding="ascii") as listing:
            children = [int(word) for word in listing.read().split()]
    except OSError:
        pass
    return children


class ChunkingServer:
    """A device server that sends each answer in ``chunk``-byte TCP segments, ``pause`` apart.

    It proves the gateway frames answers by length and CRC, not by segments.
    Optionally it answers a user function code itself (``extra``: request PDU
    prefix to raw RTU answer) so that an answer of unknown length crosses it.
    """

    def __init__(self, path: str, chunk: int, pause: float) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.listener.getsockname()[1])
        self.path = path
        self.chunk = chunk
        self.pause = pause
        self.extra: dict[bytes, bytes] = {}
        self.connections = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="chunking-server", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        serial_fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(serial_fd)
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select([self.listener], [], [], 0.1)
                if not readable:
                    continue
                conn, _ = self.listener.accept()
                self.connections += 1
                with conn:
                    self._serve(conn, serial_fd)
        finally:
            os.close(serial_fd)

    def _serve(self, conn: socket.socket, serial_fd: int) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while not self._stop.is_set():
            readable, _, _ = select.select([conn.fileno(), serial_fd], [], [], 0.1)
            if conn.fileno() in readable:
                data = conn.recv(4096)
                if not data:
                    return
                answer = next((v for k, v in self.extra.items() if data[1:].startswith(k)), None)
                if answer is not None:
                    self._send(conn, answer)
                else:
                    os.write(serial_fd, data)
            if serial_fd in readable:
                self._send(conn, os.read(serial_fd, 4096))

    def _send(self, conn: socket.socket, data: bytes) -> None:
        for start in range(0, len(data), self.chunk):
            conn.sendall(data[start : start + self.chunk])
            if start + self.chunk < len(data):
                time.sleep(self.pause)  # pacing the segments, not synchronising the test

    def close(self) -> None:
        self._stop.set()
        self._thread.join(DEADLINE_S)
        self.listener.close()


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def socat_line(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> Iterator[tuple[SimBus, Socat, RunningGateway]]:
    """A simulated PLC (unit 1) and ZL-69X (unit 2) behind socat; a gateway connected to it."""
    with ExitStack() as stack:
        sim = make_sim({1: plc(1), 2: zl69x(2)})
        server = Socat(free_port(), sim.path)
        server.start()
        stack.callback(server.kill)
        gateway = make_gateway({"lines": {"net": line_table(f"127.0.0.1:{server.port}", [1, 2])}})
        stack.callback(gateway.stop)
        wait_until(lambda: line_up(gateway))
        yield sim, server, gateway


def line_up(gateway: RunningGateway) -> bool:
    """True once the gateway is connected to the device server (it connects in the background)."""
    return gateway.call(lambda: gateway.gateway.buses["net"].up)


# --------------------------------------------------------------------------- every function code

#: One request of every function code the gateway forwards, in an order whose answers are
#: deterministic for a fresh ``plc(1)`` (the counters of FC 8, 11, 12 included).
EVERY_FUNCTION = [
    h("01 0013 0013"), h("02 00C4 0016"), h("03 0000 000A"), h("03 03E8 007D"), h("04 0008 0001"),
    h("05 00AC FF00"), h("01 00AC 0001"), h("06 0001 1234"), h("0F 0006 0009 02 1101"),
    h("10 0BB8 0003 06 0001 0002 0003"), h("03 0BB8 0003"), h("16 0004 00F2 0025"),
    h("17 000E 0003 000F 0002 04 ABCD 1234"), h("07"), h("08 0000 A537"), h("08 000E 0000"),
    h("0B"), h("0C"), h("11"), h("14 0E 06 0004 0001 0002 06 0003 0009 0002"),
    h("15 0D 06 0004 0007 0003 06AF 04BE 100D"), h("18 04DE"), h("2B 0E 01 00"),
    h("2B 0E 04 01"), h("03 FFFF 0002"),  # the last: an exception from the device
]  # fmt: skip


def ask_all(gateway: RunningGateway, unit: int) -> list[bytes]:
    with gateway.connect() as client:
        return [client.request(unit, pdu) for pdu in EVERY_FUNCTION]


def test_every_function_code_through_socat_matches_a_serial_line(
    socat_line: tuple[SimBus, Socat, RunningGateway],
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
) -> None:
    sim, _, gateway = socat_line
    over_tcp = ask_all(gateway, 1)
    reference_sim = make_sim({1: plc(1)})
    reference = make_gateway({"lines": {"a": reference_sim.line_table([1])}})
    on_serial = ask_all(reference, 1)
    for request, got, want in zip(EVERY_FUNCTION, over_tcp, on_serial, strict=True):
        assert got == want, request.hex(" ")
    assert [reply[0] & 0x80 for reply in over_tcp[:-1]] == [0] * (len(EVERY_FUNCTION) - 1)
    assert over_tcp[-1] == h("83 02")
    assert over_tcp[2] == h("03 14") + pack_registers([0, 2, 4, 6, 8, 10, 0, 0, 0, 0])
    assert sim.device(1).holding.read(3000, 3) == [1, 2, 3]
    assert sim.stats().crc_errors_in == 0


def test_answers_cut_into_small_segments_are_framed_by_length(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    server = ChunkingServer(sim.path, chunk=3, pause=0.004)
    try:
        # A user function code the device server answers itself with 9 bytes in 3 segments:
        # its length cannot be predicted, so only silence (50 ms by default) ends it.
        server.extra[h("41")] = _rtu(h("01 41 AA BB CC DD"))
        gateway = make_gateway({"lines": {"net": line_table(f"127.0.0.1:{server.port}", [1])}})
        wait_until(lambda: line_up(gateway))
        with gateway.connect() as client:
            for address in (0, 1000, 1100):
                quantity = 125 if address else 10
                reply = client.request(1, h("03") + address.to_bytes(2, "big")
                                       + quantity.to_bytes(2, "big"))  # fmt: skip
                assert reply == bytes((3, 2 * quantity)) + pack_registers(
                    sim.device(1).holding.read(address, quantity)
                )
            assert client.request(1, h("41 01")) == h("41 AA BB CC DD")
            assert client.request(1, h("06 0002 4321")) == h("06 0002 4321")
        assert server.connections == 1
    finally:
        server.close()


def _rtu(body: bytes) -> bytes:
    return append_crc(body)


def test_pymodbus_rtu_over_tcp_server_as_the_device_server(make_gateway: GatewayFactory) -> None:
    from pymodbus import FramerType
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    port = free_port()
    device = SimDevice(
        id=7,
        simdata=(
            [SimData(0, values=[i % 3 == 0 for i in range(32)], datatype=DataType.BITS)],
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, values=[10 * i for i in range(32)], datatype=DataType.REGISTERS)],
            [SimData(0, count=16, values=0, datatype=DataType.REGISTERS)],
        ),
    )
    loop = asyncio.new_event_loop()
    server: Any = None
    ready = threading.Event()

    async def start() -> None:
        nonlocal server
        server = ModbusTcpServer(device, framer=FramerType.RTU, address=("127.0.0.1", port))
        await server.serve_forever(background=True)

    def serve() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(start())
        ready.set()
        loop.run_forever()

    thread = threading.Thread(target=serve, name="pymodbus-rtu-over-tcp", daemon=True)
    thread.start()
    assert ready.wait(DEADLINE_S)
    try:
        gateway = make_gateway({"lines": {"net": line_table(f"127.0.0.1:{port}", [7])}})
        wait_until(lambda: line_up(gateway))
        with gateway.connect() as client:
            assert client.request(7, h("03 0000 0004")) == h("03 08") + pack_registers(
                [0, 10, 20, 30]
            )
            assert client.request(7, h("10 0002 0002 04 1111 2222")) == h("10 0002 0002")
            assert client.request(7, h("06 0005 ABCD")) == h("06 0005 ABCD")
            assert client.request(7, h("03 0001 0005")) == h("03 0A") + pack_registers(
                [10, 0x1111, 0x2222, 40, 0xABCD]
            )
            assert client.request(7, h("01 0000 000A")) == h("01 02 49 02")
            assert client.request(7, h("05 0001 FF00")) == h("05 0001 FF00")
            assert client.request(7, h("01 0000 000A")) == h("01 02 4B 02")
            assert client.request(7, h("03 0100 0001")) == h("83 02")
        gateway.stop()
    finally:
        asyncio.run_coroutine_threadsafe(server.shutdown(), loop).result(DEADLINE_S)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(DEADLINE_S)
        loop.close()


# --------------------------------------------------------------------------- connection loss


def test_device_server_absent_then_present(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    port = free_port()
    gateway = make_gateway({"lines": {"net": line_table(f"127.0.0.1:{port}", [1])}})
    with gateway.connect() as client:
        assert client.request(1, h("03 0000 0001")) == h("83 0A")  # nobody there: 0x0A
        server = Socat(port, sim.path)
        server.start()
        try:
            wait_until(lambda: line_up(gateway))
            assert client.request(1, h("03 0001 0001")) == h("03 02 0002")
        finally:
            server.kill()
        wait_until(lambda: not line_up(gateway))
        assert client.request(1, h("03 0000 0001")) == h("83 0A")


def test_device_server_killed_and_restarted_under_load(
    socat_line: tuple[SimBus, Socat, RunningGateway],
) -> None:
    _, server, gateway = socat_line
    masters = 4
    stop = threading.Event()
    wrong: list[str] = []
    answered: list[int] = [0] * masters
    unavailable: list[int] = [0] * masters

    def master(index: int) -> None:
        try:
            with gateway.connect() as client:
                round_ = 0
                while not stop.is_set():
                    address = 1000 + 100 * index + round_ % 50
                    quantity = 1 + (round_ + index) % 40
                    reply = client.request(1, h("03") + address.to_bytes(2, "big")
                                           + quantity.to_bytes(2, "big"))  # fmt: skip
                    expected = bytes((3, 2 * quantity)) + pack_registers(
                        list(range(address, address + quantity))
                    )
                    if reply == expected:
                        answered[index] += 1
                    elif reply in (h("83 0A"), h("83 0B")):
                        unavailable[index] += 1
                    else:
                        wrong.append(f"{address} {quantity}: {reply.hex()}")
                    round_ += 1
        except (AssertionError, OSError) as error:
            wrong.append(f"master {index}: {error!r}")

    threads = [threading.Thread(target=master, args=(i,)) for i in range(masters)]
    for thread in threads:
        thread.start()
    try:
        for _ in range(3):
            goal = sum(answered) + 50
            wait_until(lambda: sum(answered) >= goal)  # noqa: B023 (called before goal changes)
            server.kill()
            wait_until(lambda: not line_up(gateway))
            server.start()
            wait_until(lambda: line_up(gateway))
        before = sum(answered)
        wait_until(lambda: sum(answered) >= before + 50)
    finally:
        stop.set()
        for thread in threads:
            thread.join(DEADLINE_S)
    assert wrong == []
    assert all(count > 0 for count in answered), answered
    registry = gateway.gateway.metrics.registry
    lost = gateway.call(
        lambda: registry.get_sample_value("modbus_gateway_line_lost_total", {"line": "net"})
    )
    assert lost == 3
    kind = {"line": "net", "kind": "rtu-over-tcp"}
    assert gateway.call(lambda: registry.get_sample_value("modbus_gateway_line_info", kind)) == 1
