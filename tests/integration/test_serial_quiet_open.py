"""Receive-only opening (``open_serial(line, quiet=True)``): a standby's port must not drive
the bus, and must still hear it.

Pseudo-terminals have no modem lines and no kernel RS485 mode: the RS485 ioctl answers
ENOTTY there and is skipped (``set_rs485_receive`` returns ``False``), as on USB adapters
that switch direction themselves. What these tests show on a real pty: the quiet call
path opens, reads the bus, keeps every other setting and error as a normal open does,
and asks pyserial for RTS and DTR low instead of raised.
"""

from __future__ import annotations

import os
import select

import pytest

from gateway.config import LineConfig, build_config
from gateway.io.links.serial_port import (
    SerialPortError,
    check_device_usable,
    open_serial,
    set_rs485_receive,
)
from gateway.sim import open_pty_pair
from tests.helpers import DEADLINE_S

FRAME = bytes.fromhex("01 03 0000 000A C5CD")


def _line(path: str, **settings: object) -> LineConfig:
    return build_config({"lines": {"a": {"device": path, **settings}}}).lines[0]


def test_a_quiet_port_opens_and_hears_the_bus() -> None:
    with open_pty_pair() as pair:
        port = open_serial(_line(pair.path), quiet=True)
        try:
            assert port.is_open
            assert (port.rts, port.dtr) == (False, False)  # applied by the open, not raised
            os.write(pair.sim_fd, FRAME)  # another master's frame on the bus
            heard = b""
            while len(heard) < len(FRAME):
                readable, _, _ = select.select([port.fileno()], [], [], DEADLINE_S)
                assert readable, f"only {heard.hex(' ')} heard"
                heard += port.read(64)
            assert heard == FRAME
        finally:
            port.close()


def test_a_normal_open_still_raises_rts_and_dtr() -> None:
    """The default is unchanged: an active gateway's port opens as before."""
    with open_pty_pair() as pair:
        port = open_serial(_line(pair.path))
        try:
            assert (port.rts, port.dtr) == (True, True)
        finally:
            port.close()


def test_the_rs485_ioctl_is_skipped_where_the_driver_has_no_rs485_mode() -> None:
    with open_pty_pair() as pair:
        fd = os.open(pair.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            assert set_rs485_receive(fd, _line(pair.path)) is False  # ENOTTY on a pty
        finally:
            os.close(fd)
    read_end, write_end = os.pipe()  # not a terminal at all: ENOTTY as well
    try:
        assert set_rs485_receive(read_end, _line("/dev/null")) is False
    finally:
        os.close(read_end)
        os.close(write_end)


def test_a_quiet_open_reports_a_refused_setting_as_a_normal_open_does() -> None:
    with open_pty_pair() as pair, pytest.raises(SerialPortError) as caught:
        open_serial(_line(pair.path, rs485=True), quiet=True)
    assert "lines.a.rs485" in str(caught.value)


def test_the_start_check_can_open_quietly_and_releases_the_device() -> None:
    with open_pty_pair() as pair:
        line = _line(pair.path)
        check_device_usable(line, quiet=True)
        port = open_serial(line, quiet=True)  # released: it opens again
        port.close()
