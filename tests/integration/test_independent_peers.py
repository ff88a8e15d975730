"""Someone else's reading of the specification on each end of the gateway.

pymodbus (a test dependency only) as the Modbus TCP master and as the RTU
serial slave, and Debian's ``mbpoll`` as the master: if our framing, CRC,
timing or routing were off in a way our own simulator shares, these would
not agree with us.
"""

from __future__ import annotations

import os
import re
import select
import subprocess
import threading
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest

from gateway.sim import PtyPair, open_pty_pair, plc, zl69x
from gateway.sim.device import pack_registers
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    GatewayOnSim,
    Reply,
    RunningGateway,
    h,
    require_tool,
)
from tests.integration.pymodbus_harness import PymodbusServerThread, sim_device

# --------------------------------------------------------------------------- pymodbus as master


def test_pymodbus_tcp_client_through_the_gateway(gateway_with: GatewayOnSim) -> None:
    from pymodbus.client import ModbusTcpClient

    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    device = sim.device(1)
    host, port = gw.address
    client: Any = ModbusTcpClient(host, port=port, timeout=5, retries=0)  # partly untyped
    assert client.connect()
    try:
        result = client.read_holding_registers(0, count=10, device_id=1)
        assert not result.isError() and result.registers == [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
        result = client.read_holding_registers(1000, count=125, device_id=1)
        assert result.registers == list(range(1000, 1125))
        assert not client.write_registers(100, [7, 8, 9], device_id=1).isError()
        assert device.holding.read(100, 3) == [7, 8, 9]
        assert not client.write_register(103, 0xCAFE, device_id=1).isError()
        assert device.holding[103] == 0xCAFE
        assert client.read_input_registers(8, count=1, device_id=1).registers == [0x000A]

        coils = client.read_coils(19, count=19, device_id=1)
        assert coils.bits[:19] == [bool((0x056BCD >> i) & 1) for i in range(19)]
        assert not client.write_coils(40, [True, False, True, True], device_id=1).isError()
        assert device.coils.read(40, 4) == [1, 0, 1, 1]
        assert not client.write_coil(50, True, device_id=1).isError()
        assert device.coils[50] == 1
        inputs = client.read_discrete_inputs(196, count=22, device_id=1)
        assert inputs.bits[:22] == [bool((0x35DBAC >> i) & 1) for i in range(22)]

        # The ZL-69X through the same connection; its exceptions reach pymodbus intact.
        assert client.read_holding_registers(0, count=2, device_id=2).registers == [275, 0xFF9D]
        refused = client.read_discrete_inputs(0, count=1, device_id=2)
        assert refused.isError() and refused.exception_code == 0x01
        identity = client.read_device_information(read_code=1, object_id=0, device_id=2)
        assert identity.information[1] == b"ZL-69X"
        # The gateway's own exception for a unit it has no route for.
        unrouted = client.read_holding_registers(0, count=1, device_id=9)
        assert unrouted.isError() and unrouted.exception_code == 0x0A
    finally:
        client.close()
    assert sim.stats().crc_errors_in == 0


# --------------------------------------------------------------------------- pymodbus as slave


class PtyBridge:
    """Two pty pairs joined back to back: a null-modem cable between two device paths."""

    def __init__(self) -> None:
        self.left: PtyPair = open_pty_pair()
        self.right: PtyPair = open_pty_pair()
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-bridge", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ends = {self.left.sim_fd: self.right.sim_fd, self.right.sim_fd: self.left.sim_fd}
        while not self._stop.is_set():
            readable, _, _ = select.select([*ends, self._wake_r], [], [])
            for fd in readable:
                if fd == self._wake_r:
                    continue
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, OSError):
                    continue  # nobody has that end open yet (EIO): poll again
                if data:
                    os.write(ends[fd], data)

    def close(self) -> None:
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(DEADLINE_S)
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
        self.left.close()
        self.right.close()


class PymodbusSlave(PymodbusServerThread):
    """pymodbus's RTU server on a device path, on its own event loop in a thread."""

    def __init__(
        self,
        path: str,
        unit: int,
        holding: list[int],
        coils: list[bool],
        framing: str = "rtu",
    ) -> None:
        from pymodbus import FramerType
        from pymodbus.server import ModbusSerialServer

        device = sim_device(unit, coils, holding)
        # 8N1 for ASCII too: ptys refuse some parity settings (FIELD-NOTES).
        framer = FramerType.ASCII if framing == "ascii" else FramerType.RTU
        super().__init__(
            lambda: ModbusSerialServer(device, port=path, baudrate=115200, framer=framer),
            "pymodbus-slave",
        )


@pytest.fixture(params=["rtu", "ascii"])
def pymodbus_slave_line(
    make_gateway: GatewayFactory, request: pytest.FixtureRequest
) -> Iterator[tuple[PymodbusSlave, RunningGateway]]:
    """Our gateway on one end of a pty bridge, pymodbus as slave 5 on the other.

    Once on an RTU line, once on an ASCII line (8N1 on ptys, which refuse some parities).
    """
    framing: str = request.param
    with ExitStack() as stack:
        bridge = PtyBridge()
        stack.callback(bridge.close)
        slave = PymodbusSlave(
            bridge.right.path,
            5,
            holding=[10 * i for i in range(32)],
            coils=[i % 3 == 0 for i in range(32)],
            framing=framing,
        )
        stack.callback(slave.close)
        table = {"device": bridge.left.path, "baudrate": 115200, "units": [5], "timeout": 0.5}
        if framing == "ascii":
            table.update(kind="ascii", data_bits=8, parity="N")
        gateway = make_gateway({"lines": {"a": table}})
        stack.callback(gateway.stop)  # first: before the slave and the ptys go
        yield slave, gateway


def test_pymodbus_rtu_slave_behind_the_gateway(
    pymodbus_slave_line: tuple[PymodbusSlave, RunningGateway],
) -> None:
    _, gw = pymodbus_slave_line
    with gw.connect() as client:
        tid = client.send(5, h("03 0000 0008"), tid=0x0505)
        assert client.receive() == Reply(
            tid, 5, h("03 10") + pack_registers([0, 10, 20, 30, 40, 50, 60, 70])
        )
        assert client.request(5, h("10 0002 0003 06 1111 2222 3333")) == h("10 0002 0003")
        assert client.request(5, h("06 0006 ABCD")) == h("06 0006 ABCD")
        assert client.request(5, h("03 0001 0006")) == h("03 0C") + pack_registers(
            [10, 0x1111, 0x2222, 0x3333, 50, 0xABCD]
        )
        # Coils 0..9: every third set (1001 0010 01), written and read back.
        assert client.request(5, h("01 0000 000A")) == h("01 02 49 02")
        assert client.request(5, h("05 0001 FF00")) == h("05 0001 FF00")
        assert client.request(5, h("0F 0008 0002 01 03")) == h("0F 0008 0002")
        assert client.request(5, h("01 0000 000A")) == h("01 02 4B 03")
        # pymodbus's own exception for an address it does not have passes through.
        reply = client.request(5, h("03 0100 0001"))
        assert reply == h("83 02")


def test_pymodbus_on_both_ends(pymodbus_slave_line: tuple[PymodbusSlave, RunningGateway]) -> None:
    from pymodbus.client import ModbusTcpClient

    _, gw = pymodbus_slave_line
    host, port = gw.address
    client: Any = ModbusTcpClient(host, port=port, timeout=5, retries=0)  # partly untyped
    assert client.connect()
    try:
        assert client.read_holding_registers(20, count=4, device_id=5).registers == [
            200,
            210,
            220,
            230,
        ]
        assert not client.write_registers(20, [1, 2, 3, 4], device_id=5).isError()
        assert client.read_holding_registers(18, count=8, device_id=5).registers == [
            180,
            190,
            1,
            2,
            3,
            4,
            240,
            250,
        ]
        bits = client.read_coils(0, count=12, device_id=5).bits[:12]
        assert bits == [i % 3 == 0 for i in range(12)]
    finally:
        client.close()


# --------------------------------------------------------------------------- mbpoll as master


def mbpoll(*args: Any) -> str:
    """Run Debian's mbpoll once; return its standard output."""
    tool = require_tool("mbpoll")
    done = subprocess.run(
        [tool, *map(str, args)], capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0, f"mbpoll failed ({done.returncode}): {done.stdout}{done.stderr}"
    return done.stdout


def values(output: str) -> dict[int, int]:
    """``[ref]: value`` lines of mbpoll's output."""
    return {
        int(ref): int(value) for ref, value in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", output, re.M)
    }


def test_mbpoll_reads_and_writes_through_the_gateway(gateway_with: GatewayOnSim) -> None:
    require_tool("mbpoll")
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    device = sim.device(1)
    port = gw.port
    common = ("-m", "tcp", "-p", port)
    out = mbpoll(*common, "-a", 1, "-r", 1, "-c", 10, "-t", 4, "-1", "127.0.0.1")
    assert values(out) == {ref: [0, 2, 4, 6, 8, 10, 0, 0, 0, 0][ref - 1] for ref in range(1, 11)}
    out = mbpoll(*common, "-a", 1, "-r", 1001, "-c", 5, "-t", 4, "-1", "127.0.0.1")
    assert values(out) == {1001 + i: 1000 + i for i in range(5)}
    # The ZL-69X: 27.5 C and -9.9 C (0xFF9D; mbpoll prints -t 4 unsigned).
    out = mbpoll(*common, "-a", 2, "-r", 1, "-c", 2, "-t", 4, "-1", "127.0.0.1")
    assert values(out) == {1: 275, 2: 0xFF9D}
    # Writes: holding registers 501..503, then coil 41.
    mbpoll(*common, "-a", 1, "-r", 501, "-t", 4, "127.0.0.1", 11, 22, 33)
    assert device.holding.read(500, 3) == [11, 22, 33]
    mbpoll(*common, "-a", 1, "-r", 41, "-t", 0, "127.0.0.1", 1)
    assert device.coils[40] == 1
    out = mbpoll(*common, "-a", 1, "-r", 20, "-c", 19, "-t", 0, "-1", "127.0.0.1")
    assert values(out) == {20 + i: (0x056BCD >> i) & 1 for i in range(19)}
    out = mbpoll(*common, "-a", 1, "-r", 9, "-c", 1, "-t", 3, "-1", "127.0.0.1")
    assert values(out) == {9: 10}
