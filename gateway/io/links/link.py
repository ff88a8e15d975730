"""A line's byte link: the serial port, a TCP connection, or a TLS session with a slave.

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

``TlsLink`` carries a ``kind = "tls"`` line (Modbus/TCP Security): the same socket
wrapped in an ``ssl.SSLSocket`` after a non-blocking handshake (``connect_tls``), so
that the slave's alerts keep their reason (the loop's TLS transports report a
refused certificate as a plain close).
Under TLS 1.3 the slave judges the gateway's certificate after the client's side of
the handshake is done, so a refusal can arrive as the first thing read: until the
first bytes from the slave the link is not ``confirmed``, and ``Bus`` takes its loss
before then (an alert, or a plain close: asyncio's and uvloop's TLS servers close
without sending their alert) for a handshake failure, not for the loss of a working
line.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import ssl
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


# The serial port's errors live here, not in ``serial_port``: that module compiles in the
# compiled build, and mypyc compiles no subclass of a built-in exception such as OSError.
class SerialPortError(LinkError):
    """A serial line that cannot be opened or configured, with the setting to blame."""


class DeviceBusyError(SerialPortError):
    """The device is held by another program (or another line of this gateway)."""


class DeviceUnusableError(SerialPortError):
    """A device that exists but cannot serve its line: not a terminal, permission denied, or
    a setting it refuses. Retrying cannot fix it, so a start stops with the fix.

    ``key`` is the line's setting to change (``device``, ``data_bits``, ...): ``told``
    names it as the user gave it, a configuration key or a command-line flag.
    """

    def __init__(self, line: str, key: str, problem: str, fix: str) -> None:
        self.line = line
        self.key = key
        self.problem = problem
        self.fix = fix  #: may name the setting as ``{setting}``
        super().__init__(self.told(f"lines.{line}.{key}"))

    def told(self, setting: str) -> str:
        """The whole sentence, naming the setting to change as ``setting``."""
        return f"line {self.line!r}: {self.problem}; {self.fix.format(setting=setting)}."


class ListenerDeviceUnusableError(DeviceUnusableError):
    """The same for the device of a ``serial-slave`` listener (the gateway answering
    masters on a serial line): its setting is the listener's key, ``key_prefix`` + ``key``
    (``listeners[0].device``), or the flag that set it."""

    def __init__(self, listener: str, key_prefix: str, key: str, problem: str, fix: str) -> None:
        self.key_prefix = key_prefix
        super().__init__(listener, key, problem, fix)
        self.args = (self.told(f"{key_prefix}{key}"),)

    def told(self, setting: str) -> str:
        """The whole sentence, naming the listener and the setting to change as ``setting``."""
        return f"listener {self.line!r}: {self.problem}; {self.fix.format(setting=setting)}."


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


class TlsLink(TcpLink):
    """A TLS session with a Modbus/TCP Security slave: ``TcpLink`` on a non-blocking SSLSocket.

    Reads drain what OpenSSL has already decrypted (``pending``), since the socket
    may not become readable again for it; a read that yields no application data
    (a TLS 1.3 session ticket) is no event. An alert from the slave surfaces as the
    ``ssl.SSLError`` it is, with its reason, through ``on_lost``.
    """

    def __init__(
        self,
        sock: ssl.SSLSocket,
        where: str,
        loop: asyncio.AbstractEventLoop,
        on_data: Callable[[bytes], None],
        on_lost: Callable[[OSError], None],
    ) -> None:
        self._tls = sock
        #: True once the slave sent anything: it accepted the gateway's certificate.
        self.confirmed = False
        #: Called once, at the first bytes from the slave.
        self.on_confirmed: Callable[[], None] | None = None
        super().__init__(sock, where, loop, on_data, on_lost)

    def _readable(self) -> None:
        sock = self._tls
        data = b""
        failure: OSError | None = None
        try:
            chunk = sock.recv(_READ_CHUNK)
            data = chunk
            while chunk and sock.pending():
                chunk = sock.recv(_READ_CHUNK)
                data += chunk
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError, InterruptedError):
            if not data:
                return  # a record without application data (a session ticket), or a part
        except OSError as error:
            failure = error
        if data:
            if not self.confirmed:
                self.confirmed = True
                if self.on_confirmed is not None:
                    self.on_confirmed()
            self.on_data(data)
        if failure is not None:
            self._lost(failure)
        elif not data:
            self._lost(OSError("the slave closed the connection"))


async def connect_tls(
    sock: socket.socket, context: ssl.SSLContext, server_name: str, timeout: float
) -> ssl.SSLSocket:
    """Run the TLS handshake on a connected non-blocking socket, within ``timeout``.

    Raises ``OSError`` (``ssl.SSLError``, ``TimeoutError``) when it fails, and then
    closes the socket.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    try:
        tls = context.wrap_socket(sock, server_hostname=server_name, do_handshake_on_connect=False)
    except (ValueError, UnicodeError) as error:  # config checks the name; a last guard
        sock.close()
        raise ssl.SSLError(f"cannot check the name {server_name!r}: {error}") from error
    try:
        while True:
            try:
                tls.do_handshake()
                return tls
            except ssl.SSLWantReadError:
                await _ready(loop, tls.fileno(), True, deadline)
            except ssl.SSLWantWriteError:
                await _ready(loop, tls.fileno(), False, deadline)
    except BaseException:
        tls.close()
        raise


async def _ready(loop: asyncio.AbstractEventLoop, fd: int, read: bool, deadline: float) -> None:
    """Wait until ``fd`` is readable (or writable) or ``deadline`` passes (``TimeoutError``)."""
    ready: asyncio.Future[None] = loop.create_future()

    def wake() -> None:
        if not ready.done():
            ready.set_result(None)

    (loop.add_reader if read else loop.add_writer)(fd, wake)
    try:
        remaining = deadline - loop.time()
        if remaining <= 0:
            raise TimeoutError("no complete TLS handshake in time")
        try:
            await asyncio.wait_for(ready, remaining)
        except TimeoutError:
            raise TimeoutError("no complete TLS handshake in time") from None
    finally:
        (loop.remove_reader if read else loop.remove_writer)(fd)
