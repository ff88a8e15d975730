"""The kernel's error counters of a serial port (``TIOCGICOUNT``), where the driver keeps them.

A UART counts what never reaches the gateway as bytes: framing errors (wrong baud rate or
format, a noisy line), parity errors, receive overruns (the host read too late) and
breaks. Linux hands them out with the ``TIOCGICOUNT`` ioctl; a pseudo-terminal, a USB
adapter whose driver keeps none, or another system answers ``None``.
"""

from __future__ import annotations

import enum
import fcntl
import struct
import sys

#: ``TIOCGICOUNT`` from <asm-generic/ioctls.h> (Linux; the same on x86, ARM and RISC-V).
TIOCGICOUNT = 0x545D
#: ``struct serial_icounter_struct``: cts dsr rng dcd rx tx frame overrun parity brk
#: buf_overrun reserved[9], all ``int``.
_ICOUNT = struct.Struct("20i")


class UartError(enum.StrEnum):
    """The ``kind`` label of ``uart_errors_total``: one kernel counter each."""

    FRAME = "frame"
    PARITY = "parity"
    OVERRUN = "overrun"
    BREAK = "break"


#: Each kind's index in ``serial_icounter_struct`` (``overrun`` adds ``buf_overrun``).
_INDEX = {UartError.FRAME: 6, UartError.OVERRUN: 7, UartError.PARITY: 8, UartError.BREAK: 9}
_BUF_OVERRUN = 10


def uart_errors(fd: int) -> dict[UartError, int] | None:
    """The port's error counters since the driver loaded, ``None`` where it gives none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        raw = fcntl.ioctl(fd, TIOCGICOUNT, bytes(_ICOUNT.size))
    except OSError:  # ENOTTY, EINVAL (a pty), EIO (the adapter went away)
        return None
    values = _ICOUNT.unpack(raw)
    counts = {kind: values[index] for kind, index in _INDEX.items()}
    counts[UartError.OVERRUN] += values[_BUF_OVERRUN]
    return counts
