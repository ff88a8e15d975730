"""A line's byte link: the serial port, or a TCP connection to a serial device server.

Theory of operation: ``Bus`` drives every line's core the same way whatever carries
its bytes. A link delivers what it reads through ``on_data`` (one non-blocking read
per readiness, from ``loop.add_reader``), writes whole frames with ``write``, and
reports its loss once through ``on_lost`` (and raises ``LinkError`` from the write
that found it). ``SerialLink`` (``serial_port.py``) is one; ``TcpLink`` here is the
other: RTU frames over a raw TCP socket (Moxa NPort "TCP server" mode and the like).

TCP carries a byte stream: segment boundaries mean nothing, so the core frames
answers by their predicted length and CRC exactly as on a serial line, and only
an answer of unknown length ends on silence (``silence``, 50 ms by default on a
network line). ``TCP_NODELAY`` keeps a request from waiting for an ACK behind
Nagle's algorithm, and keepalive probes notice a device server that vanished
without closing.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import Callable
from typing import Protocol

_READ_CHUNK = 4096
#: Keepalive: first probe after 10 s idle, then every 5 s, lost after 3 unanswered.
_KEEPALIVE = (
    (getattr(socket, "TCP_KEEPIDLE", None), 10),
    (getattr(socket, "TCP_KEEPINTVL", None), 5),
    (getattr(socket, "TCP_KEEPCNT", None), 3),
)


class LinkError(OSError):
    """A line's link failed or is closed; the line is down until it is reopened."""


class Link(Protocol):
    """What ``Bus`` needs from whatever carries a line's bytes."""

    @property
    def closed(self) -> bool: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class TcpLink:
    """A connected, non-blocking TCP socket driven by the event loop."""

    def __init__(
        self,
        sock: socket.socket,
        where: str,
        loop: asyncio.AbstractEventLoop,
        on_data: Callable[[bytes], None],
        on_lost: Callable[[OSError], None],
    ) -> None:
        self._sock = sock
        self._where = where
        self._loop = loop
        self.on_data = on_data  #: may be replaced (after the connect delay)
        self.on_lost = on_lost  #: may be replaced
        self._fd = sock.fileno()
        self._closed = False
        loop.add_reader(self._fd, self._readable)

    @property
    def closed(self) -> bool:
        """True once the link was closed or lost."""
        return self._closed

    def write(self, data: bytes) -> None:
        """Send a whole frame; a frame is far smaller than the socket's send buffer."""
        if self._closed:
            raise LinkError(f"{self._where}: connection is closed")
        try:
            sent = self._sock.send(data)
            if sent < len(data):
                # The device server stopped reading (its serial side is stuck, or it is
                # gone without a FIN): a full send buffer means the link is lost.
                raise BlockingIOError("send buffer full")
        except BlockingIOError as error:
            self._lost(OSError(f"send buffer full, device server not reading: {error}"))
            raise LinkError(f"{self._where}: send buffer full, device server stuck") from error
        except OSError as error:
            self._lost(error)
            raise LinkError(f"{self._where}: send failed: {error}") from error

    def close(self) -> None:
        """Stop watching the socket and close it."""
        if self._closed:
            return
        self._closed = True
        self._loop.remove_reader(self._fd)
        self._sock.close()

    def _readable(self) -> None:
        try:
            data = self._sock.recv(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as error:
            self._lost(error)
            return
        if not data:
            self._lost(OSError("the device server closed the connection"))
            return
        self.on_data(data)

    def _lost(self, error: OSError) -> None:
        if self._closed:
            return
        self.close()
        self.on_lost(error)


async def connect_tcp(host: str, port: int, timeout: float) -> socket.socket:
    """A connected non-blocking socket with ``TCP_NODELAY`` and keepalive; raises ``OSError``.

    ``TimeoutError`` (an ``OSError``) when the connection is not made within ``timeout``.
    """
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    last: OSError = OSError(f"{host}:{port}: no address")
    for family, kind, proto, _, address in infos:
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            await asyncio.wait_for(loop.sock_connect(sock, address), timeout)
        except TimeoutError:
            sock.close()
            last = TimeoutError(f"no connection within {timeout:g} s")
            continue
        except OSError as error:
            sock.close()
            last = error
            continue
        except BaseException:
            sock.close()
            raise
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for option, value in _KEEPALIVE:
            if option is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.IPPROTO_TCP, option, value)
        return sock
    raise last
