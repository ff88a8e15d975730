"""Opening a serial line with pyserial and moving its bytes through the event loop.

A device node (``/dev/ttyUSB0``) or a pyserial URL (``socket://host:port``,
``rfc2217://host:port``) is opened once with the line settings; reads are
driven by ``loop.add_reader`` on the port's file descriptor, one non-blocking
read per readiness, so the loop never blocks on the line. Every failure to
apply a setting becomes a ``SerialPortError`` naming the setting, because a
traceback about ``termios`` helps nobody on a commissioning day.

One owner per device: two programs on one RS485 adapter interleave their frames
and corrupt each other's transactions. A device node is therefore opened
exclusively: ``TIOCEXCL`` (the kernel refuses further opens, except to root), an
advisory ``flock`` (what pyserial's ``exclusive=True`` and other tools take) and a
POSIX record lock, whose holder ``F_GETLK`` names by pid even where ``/proc/locks``
is hidden (systemd's ``ProcSubset=pid``). A device that is taken raises
``DeviceBusyError`` naming the holder.

Receive-only (``quiet``): the standby of a redundant pair shares the RS-485 bus with
the active gateway and must never drive it. Its port is opened with RTS and DTR set
low before ``open()`` (pyserial applies them inside the open, in place of raising
them), and a driver with kernel RS485 mode is put into it with RTS at its receive
level while idle (``TIOCSRS485``); a driver without that mode (USB adapters that
switch direction themselves, pseudo-terminals) answers ENOTTY or EINVAL, and is left
as it is. The kernel itself may raise DTR/RTS for the instant of ``open(2)`` on a
port whose speed is not B0; the RS485 mode, once set, survives on the port across
opens and keeps RTS at its idle level.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import logging
import os
import struct
import termios
import time
from array import array
from collections.abc import Callable
from typing import Any

import serial
import serial.rs485

from ...config import GatewayConfig, LineConfig, ListenerConfig
from .link import (
    DeviceBusyError,
    DeviceUnusableError,
    ListenerDeviceUnusableError,
    SerialPortError,
)
from .uart import UartError, uart_errors

log = logging.getLogger("gateway.io.serial_port")

_PARITIES = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}
_STOP_BITS = {
    1.0: serial.STOPBITS_ONE,
    1.5: serial.STOPBITS_ONE_POINT_FIVE,
    2.0: serial.STOPBITS_TWO,
}
_READ_CHUNK = 4096
#: How long a start tries again a device that denies permission (udev setting its mode).
PERMISSION_SETTLE_S = 3.0
_PERMISSION_POLL_S = 0.1
_MISSING = frozenset({errno.ENOENT, errno.ENODEV, errno.ENXIO})
_DENIED = frozenset({errno.EACCES, errno.EPERM})

__all__ = [
    "DeviceBusyError",
    "DeviceUnusableError",
    "ListenerDeviceUnusableError",
    "SerialLink",
    "SerialPortError",
    "check_device_free",
    "check_device_usable",
    "check_devices_usable",
    "check_listener_device_usable",
    "describe_holder",
    "open_serial",
    "set_rs485_receive",
]


# -------------------------------------------------------------------------- device ownership

#: ``struct flock`` on Linux (64-bit off_t): l_type, l_whence, l_start, l_len, l_pid.
_FLOCK = struct.Struct("hhqqi")


def _posix_lock_holder(fd: int) -> int | None:
    """Pid holding a POSIX record lock on the file that conflicts with ours, if any."""
    query = _FLOCK.pack(fcntl.F_WRLCK, os.SEEK_SET, 0, 0, 0)
    try:
        answer = fcntl.fcntl(fd, fcntl.F_GETLK, query)
    except OSError:
        return None
    l_type, _, _, _, pid = _FLOCK.unpack(answer)
    return pid if l_type != fcntl.F_UNLCK and pid > 0 else None


def _proc_locks_holders(path: str) -> list[int]:
    """Pids with a lock on ``path`` in ``/proc/locks`` (empty where it is hidden)."""
    try:
        status = os.stat(path)
        with open("/proc/locks", encoding="ascii") as table:
            entries = table.read().splitlines()
    except OSError:
        return []
    wanted = f"{os.major(status.st_dev):02x}:{os.minor(status.st_dev):02x}:{status.st_ino}"
    holders: list[int] = []
    for entry in entries:
        fields = entry.split()
        # "1: FLOCK  ADVISORY  WRITE 1234 00:05:27 0 EOF"; blocked waiters start with "->".
        if len(fields) >= 6 and fields[1] != "->" and fields[5] == wanted:
            with contextlib.suppress(ValueError):
                holders.append(int(fields[4]))
    return holders


def _command_line(pid: int) -> str:
    """What ``pid`` runs, for the message; empty when /proc does not say (another user's)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            words = cmdline.read().rstrip(b"\0").split(b"\0")
    except OSError:
        return ""
    text = " ".join(" ".join(word.decode("utf-8", "replace").split()) for word in words)
    return text if len(text) <= 120 else text[:117] + "..."


def describe_holder(path: str, fd: int | None = None) -> str:
    """``pid 1234 (modbus-gateway --config ...)``, or how to find the holder."""
    pid = _posix_lock_holder(fd) if fd is not None else None
    if pid is None:
        others = [holder for holder in _proc_locks_holders(path) if holder != os.getpid()]
        if others:
            pid = others[0]
        elif _proc_locks_holders(path):
            return "another line of this gateway"
    if pid is None:
        return f"another program (find it with: fuser -v {path})"
    command = _command_line(pid)
    return f"pid {pid} ({command})" if command else f"pid {pid}"


def _busy(line: LineConfig, holder: str) -> DeviceBusyError:
    return DeviceBusyError(
        f"line {line.name!r}: {line.device} is in use by {holder}; a serial device serves "
        f"one gateway line: stop the other program, or set lines.{line.name}.device to "
        "another device",
    )


def _lock(line: LineConfig, fd: int) -> None:
    """Take the advisory locks on an open device, or raise ``DeviceBusyError``."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.fcntl(fd, fcntl.F_SETLK, _FLOCK.pack(fcntl.F_WRLCK, os.SEEK_SET, 0, 0, 0))
    except OSError as error:
        if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise SerialPortError(
                f"line {line.name!r}: cannot lock {line.device}: {error}"
            ) from error
        raise _busy(line, describe_holder(line.device, fd)) from None


def check_device_free(line: LineConfig) -> None:
    """Raise ``DeviceBusyError`` naming the holder when another program holds the device.

    Checked at start, so that a second gateway on a device fails at once instead of
    running with a line it can never open. A device that does not exist (yet) passes:
    a USB adapter may be plugged in later. URLs (serial servers) are not locked.
    """
    if line.is_url:
        return
    try:
        fd = os.open(line.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as error:
        if error.errno == errno.EBUSY:  # TIOCEXCL by another program, and we are not root
            raise _busy(line, describe_holder(line.device)) from None
        return  # missing, no permission, ...: the line's own open reports it
    try:
        _lock(line, fd)
    finally:
        os.close(fd)  # releases the locks just taken


def _set_exclusive(fd: int, exclusive: bool) -> None:
    """TIOCEXCL / TIOCNXCL; devices that are not terminals (ENOTTY) are left alone."""
    with contextlib.suppress(OSError):
        fcntl.ioctl(fd, termios.TIOCEXCL if exclusive else termios.TIOCNXCL)


def _apply(line: LineConfig, port: Any, setting: str, value: Any, shown: object = None) -> None:
    try:
        setattr(port, setting, value)
    except (ValueError, serial.SerialException, termios.error, OSError) as error:
        shown = value if shown is None else shown
        key = _CONFIG_KEY.get(setting, setting)
        raise DeviceUnusableError(
            line.name,
            key,
            f"{line.device} cannot set {key} = {shown!r} ({_reason(error)})",
            "choose a value the adapter supports with {setting}" + _HINTS.get(key, ""),
        ) from error


_HINTS = {
    "data_bits": " (a pseudo-terminal, and many USB adapters, take 8 data bits only)",
    "rs485": " (most USB-RS485 adapters switch direction themselves: leave it off)",
}


def _reason(error: BaseException) -> str:
    """``Invalid argument`` rather than ``(22, 'Invalid argument')``."""
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    if len(error.args) == 2 and isinstance(error.args[1], str):  # termios.error(errno, text)
        return error.args[1]
    return str(error)


_CONFIG_KEY = {"bytesize": "data_bits", "stopbits": "stop_bits", "rs485_mode": "rs485"}


# ``linux/serial.h``: the RS485 ioctls and ``struct serial_rs485`` (flags, two delays,
# padding: 8 ints), as pyserial uses them.
_TIOCGRS485 = 0x542E
_TIOCSRS485 = 0x542F
_SER_RS485_ENABLED = 1 << 0
_SER_RS485_RTS_ON_SEND = 1 << 1
_SER_RS485_RTS_AFTER_SEND = 1 << 2
#: What a driver without kernel RS485 mode answers (a USB adapter, a pseudo-terminal).
_NO_RS485 = frozenset({errno.ENOTTY, errno.EINVAL, errno.EOPNOTSUPP})


def set_rs485_receive(fd: int, line: LineConfig) -> bool:
    """Put a driver with kernel RS485 mode into it, RTS at the line's receive level while
    idle (``SER_RS485_RTS_AFTER_SEND``), so the port does not drive the bus. ``False``
    when the driver has no such mode (ENOTTY, EINVAL: left as it is)."""
    settings = array("i", [0] * 8)
    try:
        fcntl.ioctl(fd, _TIOCGRS485, settings)
        flags = settings[0] | _SER_RS485_ENABLED
        flags &= ~(_SER_RS485_RTS_ON_SEND | _SER_RS485_RTS_AFTER_SEND)
        if line.rs485_rts_level_for_tx:
            flags |= _SER_RS485_RTS_ON_SEND
        if line.rs485_rts_level_for_rx:
            flags |= _SER_RS485_RTS_AFTER_SEND
        settings[0] = flags
        fcntl.ioctl(fd, _TIOCSRS485, settings)
    except OSError as error:
        if error.errno in _NO_RS485:
            return False
        raise SerialPortError(
            f"line {line.name!r}: cannot put {line.device} into RS485 receive: {error}"
        ) from error
    return True


def open_serial(line: LineConfig, *, quiet: bool = False) -> serial.SerialBase:
    """Open and configure the line's port; raise ``SerialPortError`` with the fix.

    ``quiet``: receive only (a standby's port): RTS and DTR stay low through the open, and
    kernel RS485 mode, where the driver has it, holds RTS at the receive level.
    """
    try:
        port = serial.serial_for_url(line.device, do_not_open=True)
    except (ValueError, serial.SerialException) as error:
        raise SerialPortError(
            f"line {line.name!r}: {line.device!r} is not a device path or a supported URL "
            f"(socket://, rfc2217://): {error}"
        ) from error
    port.timeout = 0
    _apply(line, port, "baudrate", line.baudrate)
    if quiet:  # applied by ``open()`` itself, in place of raising them
        port.rts = False
        port.dtr = False
    try:
        port.open()
    except (serial.SerialException, OSError) as error:
        raise _open_failure(line, error) from error
    exclusive = False
    try:
        if not line.is_url:
            fd = port.fileno()
            _lock(line, fd)
            _set_exclusive(fd, True)
            exclusive = True
            if quiet:  # only once the device is ours: never a mode change on another's
                set_rs485_receive(fd, line)
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
        if exclusive:
            _release(port)
        else:  # the device belongs to someone else: leave its TIOCEXCL alone
            with contextlib.suppress(OSError, serial.SerialException):
                port.close()
        raise
    return port


def _open_failure(line: LineConfig, error: BaseException) -> SerialPortError:
    """Why a device did not open, as the error a start stops on or a reopen retries."""
    number = getattr(error, "errno", None)
    if number == errno.EBUSY:
        return _busy(line, describe_holder(line.device))
    if number in _DENIED:
        return _denied(line)
    if number not in _MISSING and _exists_but_not_a_terminal(line.device):
        return _not_a_terminal(line)
    return SerialPortError(
        f"line {line.name!r}: cannot open {line.device}: {error}; check that the device exists "
        "(a USB adapter is opened once it is plugged in) and that the gateway's user is in "
        "the dialout group."
    )


def _exists_but_not_a_terminal(path: str) -> bool:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return False
    try:
        return not os.isatty(fd)
    finally:
        os.close(fd)


def _not_a_terminal(line: LineConfig) -> DeviceUnusableError:
    return DeviceUnusableError(
        line.name,
        "device",
        f"{line.device} is not a serial device (not a terminal)",
        "set {setting} to the adapter's device, such as /dev/ttyUSB0 or a name under "
        "/dev/serial/by-id/",
    )


def _denied(line: LineConfig, waited: float = 0.0) -> DeviceUnusableError:
    after = f" (still after {waited:g} s)" if waited else ""
    return DeviceUnusableError(
        line.name,
        "device",
        f"permission denied opening {line.device}{after}",
        "add the gateway's user to the device's group (usermod -aG dialout USER, then log in "
        "again; the systemd unit has it already), or set {setting} to a device that user may "
        "open",
    )


def check_device_usable(
    line: LineConfig,
    settle: float = PERMISSION_SETTLE_S,
    clock: Callable[[], float] = time.monotonic,
    wait: Callable[[float], None] = time.sleep,
    *,
    quiet: bool = False,
) -> None:
    """At start: raise ``DeviceUnusableError`` for a device that exists but cannot serve the
    line (not a terminal, permission denied, a setting it refuses) and ``DeviceBusyError``
    for one another program holds. A device that does not exist passes: a USB adapter may
    be plugged in later, and the line opens it then. Permission denied is tried again for
    ``settle`` seconds: udev may still be setting the mode of a device that just appeared.
    ``quiet``: the checking open is receive-only, as a standby's line opens (``open_serial``).
    """
    if line.is_url:
        return
    fd = _open_when_permitted(line, settle, clock, wait)
    if fd is None:
        return
    try:
        if not os.isatty(fd):
            raise _not_a_terminal(line)
    finally:
        os.close(fd)
    check_device_free(line)
    _release(open_serial(line, quiet=quiet))  # every setting applied once, as the line will


def check_listener_device_usable(listener: ListenerConfig) -> None:
    """``check_device_usable`` for a ``serial-slave`` listener's device, its error naming
    the listener and its key. A device that does not exist passes here too: the listener
    opens it once it is plugged in."""
    if listener.serial is None:
        return
    try:
        check_device_usable(listener.serial)
    except DeviceUnusableError as error:
        raise ListenerDeviceUnusableError(
            listener.name, listener.key_prefix, error.key, error.problem, error.fix
        ) from error


def check_devices_usable(config: GatewayConfig, *, quiet: bool = False) -> None:
    """At start, every line's device and every ``serial-slave`` listener's, before any is
    opened: one that is held or cannot be used stops the start with the fix."""
    for line in config.lines:
        check_device_usable(line, quiet=quiet)
    for listener in config.listeners:
        check_listener_device_usable(listener)


def _open_when_permitted(
    line: LineConfig, settle: float, clock: Callable[[], float], wait: Callable[[float], None]
) -> int | None:
    """The device opened, ``None`` when it does not exist; permission denied is retried."""
    deadline = clock() + settle
    told = False
    while True:
        try:
            return os.open(line.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as error:
            if error.errno in _MISSING:
                return None
            if error.errno == errno.EBUSY:
                raise _busy(line, describe_holder(line.device)) from None
            if error.errno not in _DENIED:
                raise _open_failure(line, error) from error
            if clock() >= deadline:
                raise _denied(line, settle) from None
        if not told:
            told = True
            log.info(
                "line %s: permission denied opening %s; trying again for %g s (udev may "
                "still be setting its mode)",
                line.name,
                line.device,
                settle,
            )
        wait(_PERMISSION_POLL_S)


def _release(port: serial.SerialBase) -> None:
    """Close a port, first clearing TIOCEXCL: on a pty the flag outlives our descriptor."""
    fileno = getattr(port, "fileno", None)
    if fileno is not None and port.is_open:
        with contextlib.suppress(OSError, serial.SerialException, AttributeError):
            _set_exclusive(int(fileno()), False)
    with contextlib.suppress(OSError, serial.SerialException):
        port.close()


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
        #: True once the link was closed or lost (a plain attribute: read per frame sent).
        self.closed = False
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

    def uart_errors(self) -> dict[UartError, int] | None:
        """The kernel's error counters of the port (``None`` on a pty, a socket, or closed)."""
        return None if self.closed else uart_errors(self._fd)

    def write(self, data: bytes) -> None:
        """Write a whole frame; a frame is small enough for the kernel buffer to take at once."""
        if self.closed:
            raise SerialPortError(f"{self._port.name}: line is closed")
        try:
            written = os.write(self._fd, data)  # all of it, but for a short write
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

    def close(self) -> None:
        """Stop watching the port and close it."""
        if self.closed:
            return
        self.closed = True
        self._loop.remove_reader(self._fd)
        _release(self._port)

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
        if self.closed:
            return
        self.close()
        self._on_lost(error)
