"""``kind = "tcp"``: Modbus TCP slaves behind the gateway (TCP-to-TCP proxying).

pymodbus's Modbus TCP server is the slave: an independent reading of MBAP. The gateway
numbers its own requests downstream, so a master's transaction id never reaches the
slave and the answer is matched by the gateway's id.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator

import pytest

from gateway.config import ConfigError, build_config
from gateway.sim.device import pack_registers
from tests.helpers import DEADLINE_S, GatewayFactory, RunningGateway, h
from tests.integration.metrics_harness import samples, series
from tests.integration.pymodbus_harness import PymodbusServerThread, sim_device


class PymodbusTcpSlave(PymodbusServerThread):
    """pymodbus's Modbus TCP server (unit 7) on its own loop in a thread."""

    def __init__(self) -> None:
        from pymodbus.server import ModbusTcpServer

        device = sim_device(7, [i % 3 == 0 for i in range(32)], [10 * i for i in range(32)])
        super().__init__(
            lambda: ModbusTcpServer(device, address=("127.0.0.1", 0)), "pymodbus-tcp-slave"
        )


@pytest.fixture
def tcp_slave() -> Iterator[PymodbusTcpSlave]:
    slave = PymodbusTcpSlave()
    yield slave
    slave.close()


def wait_up(gateway: RunningGateway) -> None:
    deadline = time.monotonic() + DEADLINE_S
    while not gateway.call(lambda: gateway.gateway.buses["plc"].up):
        assert time.monotonic() < deadline, "the gateway never connected to the slave"
        time.sleep(0.01)


def test_pymodbus_tcp_slave_behind_the_gateway(
    tcp_slave: PymodbusTcpSlave, make_gateway: GatewayFactory
) -> None:
    table = {"kind": "tcp", "address": f"127.0.0.1:{tcp_slave.port}", "units": [7]}
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    with gw.connect() as client:
        tid = client.send(7, h("03 0000 0004"), tid=0xBEEF)
        reply = client.receive()
        assert (reply.transaction_id, reply.pdu) == (
            tid,
            h("03 08") + pack_registers([0, 10, 20, 30]),
        )
        assert client.request(7, h("10 0002 0002 04 1111 2222")) == h("10 0002 0002")
        assert client.request(7, h("06 0005 ABCD")) == h("06 0005 ABCD")
        assert client.request(7, h("03 0001 0005")) == h("03 0A") + pack_registers(
            [10, 0x1111, 0x2222, 40, 0xABCD]
        )
        assert client.request(7, h("01 0000 000A")) == h("01 02 49 02")
        assert client.request(7, h("05 0001 FF00")) == h("05 0001 FF00")
        assert client.request(7, h("0F 0008 0002 01 03")) == h("0F 0008 0002")
        assert client.request(7, h("01 0000 000A")) == h("01 02 4B 03")
        assert client.request(7, h("03 0100 0001")) == h("83 02")  # pymodbus's own exception
    found = samples(gw)
    assert found[series("modbus_gateway_line_info", line="plc", kind="tcp")] == 1
    assert found[series("modbus_gateway_discarded_frames_total", line="plc", reason="late")] == 0


def test_a_tcp_slave_that_is_down_is_answered_0x0a(make_gateway: GatewayFactory) -> None:
    # Nothing listens on port 9 of 127.0.0.1 here (discard): the connection is refused.
    gw = make_gateway({"lines": {"plc": {"kind": "tcp", "address": "127.0.0.1:9", "units": [7]}}})
    with gw.connect() as client:
        assert client.request(7, h("03 0000 0001")) == h("83 0A")


def test_a_tcp_line_takes_an_address_not_a_device() -> None:
    with pytest.raises(ConfigError, match=r"lines\.plc\.device.*address"):
        build_config({"lines": {"plc": {"kind": "tcp", "device": "/dev/ttyUSB0", "units": [7]}}})


def test_a_slave_out_of_step_is_reconnected(make_gateway: GatewayFactory) -> None:
    """A header no Modbus TCP slave sends: the connection is dropped and made again, and the
    read on the wire is sent again on the new one."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    connections: list[int] = []

    def slave() -> None:
        for number in (1, 2):
            conn, _ = listener.accept()
            connections.append(number)
            with conn:
                request = conn.recv(260)
                if number == 1:
                    conn.sendall(request[:2] + b"\x00\x01\x00\x03\x07\x83\x02")  # protocol id 1
                    conn.recv(260)  # until the gateway closes it
                    continue
                with contextlib.suppress(OSError):  # every request, until the gateway stops
                    while request:
                        conn.sendall(request[:4] + b"\x00\x05\x07\x03\x02\x12\x34")
                        request = conn.recv(260)
        listener.close()

    thread = threading.Thread(target=slave, daemon=True)
    thread.start()
    table = {"kind": "tcp", "address": f"127.0.0.1:{port}", "units": [7], "retries": 0}
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    with gw.connect() as client:
        # The stream was dropped; the read went again on the new connection.
        assert client.request(7, h("03 0000 0001")) == h("03 02 1234")
        assert client.request(7, h("03 0000 0001")) == h("03 02 1234")
    assert connections == [1, 2]
    found = samples(gw)
    assert (
        found[series("modbus_gateway_discarded_frames_total", line="plc", reason="bad_header")] == 1
    )
    reconnects = series("modbus_gateway_line_reconnects_total", line="plc", reason="out_of_step")
    assert found[reconnects] == 1
    gw.stop()
    thread.join(DEADLINE_S)


def test_a_connection_that_stops_answering_is_made_again(make_gateway: GatewayFactory) -> None:
    """A device whose first connection hangs after 10 answers (its socket task died) but
    that serves new connections: after 3 answers missed in a row, nothing heard on it, the
    gateway reconnects, and the master's polls are served again. The timeouts on the dead
    connection do not make the slave suspect."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    connections: list[int] = []
    stop = threading.Event()

    def serve(conn: socket.socket, number: int) -> None:
        answered = 0
        with conn, contextlib.suppress(OSError):
            while not stop.is_set():
                request = conn.recv(260)
                if not request:
                    return
                if number == 1 and answered >= 10:
                    continue  # hung: reads, never answers
                conn.sendall(request[:4] + b"\x00\x05\x07\x03\x02\x12\x34")
                answered += 1

    def slave() -> None:
        listener.settimeout(DEADLINE_S)
        with contextlib.suppress(OSError):
            while not stop.is_set():
                conn, _ = listener.accept()
                connections.append(len(connections) + 1)
                threading.Thread(target=serve, args=(conn, len(connections)), daemon=True).start()

    thread = threading.Thread(target=slave, daemon=True)
    thread.start()
    table = {"kind": "tcp", "address": f"127.0.0.1:{port}", "units": [7], "retries": 0}
    gw = make_gateway({"lines": {"plc": table}})
    wait_up(gw)
    replies = []
    with gw.connect() as client:
        for _ in range(30):
            replies.append(client.request(7, h("03 0000 0001")))
    stop.set()
    listener.close()
    assert replies[:10] == [h("03 02 1234")] * 10
    assert replies[-10:] == [h("03 02 1234")] * 10  # served again on the new connection
    assert len(connections) == 2
    found = samples(gw)
    reconnects = series("modbus_gateway_line_reconnects_total", line="plc", reason="silent")
    assert found[reconnects] == 1
    assert found[series("modbus_gateway_slaves_isolated", line="plc", state="suspect")] == 0
    assert found[series("modbus_gateway_slaves_isolated", line="plc", state="down")] == 0
    gw.stop()
