"""A pseudo-terminal pair standing in for an RS485 line: simulator on one end, gateway on the other.

The simulator gets the master fd (raw, non-blocking); the gateway opens the
slave device path by name with pyserial, as it would a USB adapter. We keep
our own fd on the slave side open for the pair's lifetime: without it the
master reads EIO (and select reports it readable) whenever the gateway has the
port closed, e.g. before it opens it or while it reconnects.
"""

from __future__ import annotations

import os
import tty


class PtyPair(tuple[int, str]):
    """``(sim_fd, path)``; unpacks like a 2-tuple, and ``close()`` releases both ends."""

    hold_fd: int
    closed: bool

    def __new__(cls, sim_fd: int, path: str, hold_fd: int) -> PtyPair:
        pair = super().__new__(cls, (sim_fd, path))
        pair.hold_fd = hold_fd
        pair.closed = False
        return pair

    @property
    def sim_fd(self) -> int:
        """The master fd the simulator reads requests from and writes responses to."""
        return self[0]

    @property
    def path(self) -> str:
        """The slave device path (``/dev/pts/N``) the gateway opens."""
        return self[1]

    def close(self) -> None:
        """Close both fds; safe to call twice."""
        close_pty_pair(self)

    def __enter__(self) -> PtyPair:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def open_pty_pair() -> PtyPair:
    """Create a raw (no echo, no line discipline) pty pair; returns ``(sim_fd, path)``."""
    master, slave = os.openpty()
    try:
        path = os.ttyname(slave)
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
    except OSError:
        os.close(master)
        os.close(slave)
        raise
    return PtyPair(master, path, slave)


def close_pty_pair(pair: PtyPair) -> None:
    """Close both ends of ``pair`` once; later calls do nothing (the fd numbers may be reused)."""
    if pair.closed:
        return
    pair.closed = True
    os.close(pair.sim_fd)
    os.close(pair.hold_fd)
