"""Opening serial lines: clear errors naming the setting, and serial servers reached by URL."""

from __future__ import annotations

import os
import select
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.config import build_config
from gateway.io.links.serial_port import (
    DeviceUnusableError,
    SerialPortError,
    check_device_usable,
    open_serial,
)
from gateway.sim import SimulatedLine, open_pty_pair, plc
from tests.helpers import DEADLINE_S, GatewayFactory

READ_10 = bytes.fromhex("03 0000 000A")


@pytest.mark.parametrize(
    ("setting", "key"),
    [({"rs485": True}, "lines.a.rs485"), ({"data_bits": 7}, "lines.a.data_bits")],
    ids=["rs485", "data_bits"],
)
def test_an_unsupported_setting_is_named_in_the_error(setting: dict[str, object], key: str) -> None:
    """Pseudo-terminals refuse the RS485 ioctl and 7 data bits, like many cheap adapters."""
    with open_pty_pair() as pair:
        config = build_config({"lines": {"a": {"device": pair.path, **setting}}})
        with pytest.raises(SerialPortError) as caught:
            open_serial(config.lines[0])
    message = str(caught.value)
    assert key in message and pair.path in message
    assert "RS485Settings" not in message  # the value is shown as configured


def test_a_missing_device_says_what_to_check() -> None:
    config = build_config({"lines": {"a": {"device": "/dev/ttyNOSUCHUSB9"}}})
    with pytest.raises(SerialPortError) as caught:
        open_serial(config.lines[0])
    assert "/dev/ttyNOSUCHUSB9" in str(caught.value) and "dialout" in str(caught.value)


def test_a_line_that_cannot_be_opened_answers_0x0a(
    make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    """A device not plugged in yet: the gateway starts, and the line answers 0x0A meanwhile.

    (A device that exists but refuses a setting stops the start instead: see
    tests/e2e/test_device_errors.py.)
    """
    absent = tmp_path / "ttyUSB-not-plugged-in"
    gw = make_gateway({"lines": {"a": {"device": str(absent), "units": [1]}}})
    with gw.connect() as master:
        assert master.request(1, READ_10) == bytes([0x83, 0x0A])
    ready, why = gw.call(gw.gateway.is_ready)
    assert not ready and "a" in why


def test_an_unsupported_setting_stops_the_start() -> None:
    """Retrying cannot make a pty take the RS485 ioctl: the check at start says so."""
    with open_pty_pair() as pair:
        config = build_config({"lines": {"a": {"device": pair.path, "rs485": True}}})
        with pytest.raises(DeviceUnusableError) as caught:
            check_device_usable(config.lines[0])
    assert caught.value.key == "rs485"
    assert str(caught.value).endswith("(most USB-RS485 adapters switch direction themselves: "
                                      "leave it off).")  # fmt: skip


class SerialServer:
    """A TCP 'serial server' on 127.0.0.1 with a simulated slave behind it."""

    def __init__(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", 0))
        host, port = self._listener.getsockname()[:2]
        self.url = f"socket://{host}:{port}"
        self.connected = threading.Event()
        self.line: SimulatedLine | None = None
        self._connection: socket.socket | None = None
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        self._listener.settimeout(DEADLINE_S)
        connection, _ = self._listener.accept()
        connection.setblocking(False)
        self._connection = connection
        self.line = SimulatedLine(connection.fileno(), {1: plc(1)})
        self.line.start()
        self.connected.set()

    def close(self) -> None:
        self._thread.join(DEADLINE_S)
        if self.line is not None:
            self.line.stop()
        if self._connection is not None:
            self._connection.close()
        self._listener.close()


@pytest.fixture
def serial_server() -> Iterator[SerialServer]:
    """A serial server, closed at teardown."""
    server = SerialServer()
    yield server
    server.close()


def test_a_serial_server_reached_by_url(
    serial_server: SerialServer, make_gateway: GatewayFactory
) -> None:
    gw = make_gateway({"lines": {"a": {"device": serial_server.url, "frame_gap": 0, "units": [1]}}})
    assert serial_server.connected.wait(DEADLINE_S)
    with gw.connect() as master:
        reply = master.request(1, READ_10)
        assert reply == bytes.fromhex("03 14 0000 0002 0004 0006 0008 000A 0000 0000 0000 0000")
        assert master.request(1, bytes.fromhex("06 0003 0309")) == bytes.fromhex("06 0003 0309")
    assert serial_server.line is not None
    assert serial_server.line.devices[1].holding[3] == 0x0309


def test_a_port_lost_under_a_transaction_answers_0x0a_not_a_timeout(
    make_gateway: GatewayFactory,
) -> None:
    """The adapter disappears while a request waits for its answer: the gateway left, not
    the slave, so the master gets 0x0A at once and the slave gets no timeout on its record."""
    pair = open_pty_pair()
    try:
        gw = make_gateway({"lines": {"a": {"device": pair.path, "units": [1], "timeout": 30.0}}})
        with gw.connect() as master:
            tid = master.send(1, READ_10)
            # Nothing answers; unplug: the simulator's end goes away under the transaction.
            assert _read_request(pair.sim_fd) == bytes.fromhex("01 03 0000 000A C5CD")
            pair.close()
            reply = master.receive(timeout=5.0)
            assert (reply.transaction_id, reply.pdu) == (tid, bytes([0x83, 0x0A]))
        registry = gw.gateway.metrics.registry
        assert registry.get_sample_value("modbus_gateway_line_lost_total", {"line": "a"}) == 1
        timeouts = registry.get_sample_value(
            "modbus_gateway_timeouts_total", {"line": "a", "unit": "1"}
        )
        assert timeouts == 0
    finally:
        pair.close()


def _read_request(fd: int) -> bytes:
    """The 8 bytes of one request written by the gateway, with a deadline."""
    data = b""
    while len(data) < 8:
        assert select.select([fd], [], [], DEADLINE_S)[0], "no request reached the line"
        data += os.read(fd, 8 - len(data))
    return data
