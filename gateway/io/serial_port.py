"""Opening a serial line with pyserial and moving its bytes through the event loop.

A device node (``/dev/ttyUSB0``) or a pyserial URL (``socket://host:port``,
``rfc2217://host:port``) is opened once with the line settings; reads are
driven by ``loop.add_reader`` on the port's file descriptor, one non-blocking
read per readiness, so the loop never blocks on the line. Every failure to
apply a setting becomes a ``SerialPortError`` naming the setting, because a
traceback about ``termios`` helps nobody on a commissioning day.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import termios
from collections.abc import Callable
from typing import Any

import serial
import serial.rs485

from ..config import LineConfig

_PARITIES = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}
_STOP_BITS = {
    1.0: serial.STOPBITS_ONE,
    1.5: serial.STOPBITS_ONE_POINT_FIVE,
    2.0: serial.STOPBITS_TWO,
}
_READ_CHUNK = 4096


class SerialPortError(OSError):
    """A serial line that cannot be opened or configured, with the setting to blame."""


def _apply(line: LineConfig, port: Any, setting: str, value: Any, shown: object = None) -> None:
    try:
        setattr(port, setting, value)
    except (ValueError, serial.SerialException, termios.error, OSError) as error:
        shown = value if shown is None else shown
        raise SerialPortError(
            f"line {line.name!r} ({line.device}): cannot set {setting}={shown!r}: {error}; "
            f"check lines.{line.name}.{_CONFIG_KEY.get(setting, setting)} against what the "
            "adapter supports"
        ) from error


_CONFIG_KEY = {"bytesize": "data_bits", "stopbits": "stop_bits", "rs485_mode": "rs485"}


def open_serial(line: LineConfig) -> serial.SerialBase:
    """Open and configure the line's port; raise ``SerialPortError`` with the fix."""
    try:
        port = serial.serial_for_url(line.device, do_not_open=True)
    except (ValueError, serial.SerialException) as error:
        raise SerialPortError(
            f"line {line.name!r}: {line.device!r} is not a device path or a supported URL "
            f"(socket://, rfc2217://): {error}"
        ) from error
    port.timeout = 0
    _apply(line, port, "baudrate", line.baudrate)
    try:
        port.open()
    except (serial.SerialException, OSError) as error:
        raise SerialPortError(
            f"line {line.name!r}: cannot open {line.device}: {error}; check the device exists, "
            "is not used by another program, and that the gateway's user is in the dialout group"
        ) from error
    try:
        _apply(line, port, "bytesize", line.data_bits)
        _apply(line, port, "parity", _PARITIES[line.parity])
        _apply(line, port, "stopbits", _STOP_BITS[line.stop_bits])
        if line.rs485:
            _apply(
                line,
                port,
                "rs485_mode",
                serial.rs485.RS485Settings(
                    rts_level_for_tx=line.rs485_rts_level_for_tx,
                    rts_level_for_rx=line.rs485_rts_level_for_rx,
                    delay_before_tx=line.rs485_delay_before_tx or None,
                    delay_before_rx=line.rs485_delay_after_tx or None,
                ),
                shown=True,
            )
    except SerialPortError:
        port.close()
        raise
    return port


class SerialLink:
    """Non-blocking byte transport over an open pyserial port, driven by the event loop."""

    def __init__(
        self,
        port: serial.SerialBase,
        loop: asyncio.AbstractEventLoop,
        on_data: Callable[[bytes], None],
        on_lost: Callable[[OSError], None],
    ) -> None:
        self._port = port
        self._loop = loop
        self._on_data = on_data
        self._on_lost = on_lost
        self._fd = self._file_descriptor(port)
        self._closed = False
        loop.add_reader(self._fd, self._readable)

    @staticmethod
    def _file_descriptor(port: serial.SerialBase) -> int:
        fileno = getattr(port, "fileno", None)
        if fileno is not None:
            try:
                return int(fileno())
            except (OSError, AttributeError, serial.SerialException):
                pass
        sock = getattr(port, "_socket", None)
        if sock is not None:
            return int(sock.fileno())
        raise SerialPortError(f"{port.name}: this port type has no file descriptor to watch")

    @property
    def closed(self) -> bool:
        """True once the link was closed or lost."""
        return self._closed

    def write(self, data: bytes) -> None:
        """Write a whole frame; a frame is small enough for the kernel buffer to take at once."""
        if self._closed:
            raise SerialPortError(f"{self._port.name}: line is closed")
        written = 0
        try:
            while written < len(data):
                written += os.write(self._fd, data[written:])
        except BlockingIOError as error:
            # A frame is far smaller than the kernel's buffer: a full buffer means the
            # adapter is stuck (flow control, a hung USB device). Treat the line as lost.
            self._lost(error)
            raise SerialPortError(f"{self._port.name}: output buffer full, line stuck") from error
        except OSError as error:  # the adapter went away (EIO, ENODEV): the worker answers 0x0A
            self._lost(error)
            raise SerialPortError(f"{self._port.name}: write failed: {error}") from error

    def discard_input(self) -> int:
        """Read and drop whatever is waiting in the input buffer; return how many bytes."""
        dropped = 0
        while not self._closed:
            try:
                chunk = os.read(self._fd, _READ_CHUNK)
            except BlockingIOError:
                break
            except OSError as error:
                self._lost(error)
                break
            if not chunk:
                break
            dropped += len(chunk)
        return dropped

    def close(self) -> None:
        """Stop watching the port and close it."""
        if self._closed:
            return
        self._closed = True
        self._loop.remove_reader(self._fd)
        with contextlib.suppress(OSError, serial.SerialException):
            self._port.close()

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, _READ_CHUNK)
        except BlockingIOError:
            return
        except OSError as error:
            self._lost(error)
            return
        if not data:
            self._lost(OSError("end of file on the serial line"))
            return
        self._on_data(data)

    def _lost(self, error: OSError) -> None:
        if self._closed:
            return
        self.close()
        self._on_lost(error)
