"""Simulated Modbus TCP slaves: devices served over MBAP on a TCP listener.

Theory of operation: one asyncio server (uvloop when installed) on a loop of
its own, in a daemon thread (as ``SimulatedLine``: the simulator's timing must
not depend on the gateway's loop), or on the caller's loop with ``listen``.
Each connection's bytes go through the core's ``MbapDecoder``, so any chunking
gives the same frames; every complete request is answered at once with the
request's transaction id and unit id, answers of one read written together.
Requests pipelined on a connection are all served, in order, unless a unit's
``reply_delay`` holds its answers back (then they may overtake each other, as
a multi-threaded slave's do). A header no Modbus TCP peer sends closes the
connection. A unit id the server does not serve is answered 0x0B.

Unit ids: ``devices`` maps each id to its device (0..255). With one device
and ``direct_unit`` (the default), unit id 0xFF reaches it too: the Modbus
Messaging on TCP/IP Implementation Guide's id for a device addressed by its IP
address, which the R6 controller accepts beside 0x01.

``ssl``: an ``ssl.SSLContext`` serves Modbus/TCP Security (TLS) instead of
plain Modbus TCP on the same code.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl as ssl_module
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import cast

from gateway.core.errors import ExceptionCode, FramingError
from gateway.core.mbap import MbapDecoder, MbapFrame, encode_mbap
from gateway.core.pdu import exception_pdu

from .device import SimulatedDevice
from .line import UnitFaults

DIRECT_UNIT = 0xFF
_START_TIMEOUT_S = 10.0
_JOIN_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class TcpSlaveStats:
    """A snapshot of what the server saw and did."""

    connections: int  #: connections accepted
    requests: int  #: complete requests, for any unit id
    responses: int  #: answers written
    unknown_units: int  #: requests for a unit id not served (answered 0x0B)
    silent_drops: int  #: requests to a unit injected ``silent``
    bad_headers: int  #: connections closed for a header no Modbus TCP peer sends
    max_in_flight: int  #: most requests received on one connection and not yet answered


@dataclass
class _TcpCounters:
    connections: int = 0
    requests: int = 0
    responses: int = 0
    unknown_units: int = 0
    silent_drops: int = 0
    bad_headers: int = 0
    max_in_flight: int = 0


def _new_loop() -> asyncio.AbstractEventLoop:
    try:
        import uvloop
    except ImportError:
        return asyncio.new_event_loop()
    return uvloop.new_event_loop()


class _SlaveConnection(asyncio.Protocol):
    """One master's connection: frames in, answers out."""

    def __init__(self, server: TcpSlaveServer) -> None:
        self._server = server
        self._decoder = MbapDecoder()
        self._transport: asyncio.Transport | None = None
        self._pending = 0  # delayed answers not yet written

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)  # uvloop's is not a subclass
        self._server._counters.connections += 1
        self._server._transports.add(self._transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._transport is not None:
            self._server._transports.discard(self._transport)
        self._transport = None

    def data_received(self, data: bytes) -> None:
        decoder = self._decoder
        server = self._server
        out: list[bytes] = []
        waiting = self._pending  # delayed answers of earlier reads, still owed
        try:
            decoder.feed(data)
            frame = decoder.next_frame()
            count = 0
            while frame is not None:
                count += 1
                answer = server.answer(frame, self)
                if answer is not None:
                    out.append(answer)
                frame = decoder.next_frame()
        except FramingError:
            server._counters.bad_headers += 1
            if self._transport is not None:
                self._transport.abort()
            return
        counters = server._counters
        in_flight = count + waiting
        if in_flight > counters.max_in_flight:
            counters.max_in_flight = in_flight
        if out and self._transport is not None:
            counters.responses += len(out)
            self._transport.write(out[0] if len(out) == 1 else b"".join(out))

    def send_later(self, delay: float, adu: bytes) -> None:
        """Write ``adu`` ``delay`` seconds from now (a slow slave), if still connected."""
        self._pending += 1
        loop = asyncio.get_running_loop()
        loop.call_later(delay, self._send_delayed, adu)

    def _send_delayed(self, adu: bytes) -> None:
        self._pending -= 1
        if self._transport is not None and not self._transport.is_closing():
            self._server._counters.responses += 1
            self._transport.write(adu)


class TcpSlaveServer:
    """Answers Modbus TCP requests from ``{unit id: SimulatedDevice}``.

    ``listen`` serves on the running loop; ``SimulatedTcpSlave`` runs it in a
    thread of its own. ``faults(unit)`` may be changed while serving (``silent``,
    ``reply_delay``; the serial-only faults are ignored).
    """

    def __init__(self, devices: Mapping[int, SimulatedDevice], *, direct_unit: bool = True) -> None:
        units = dict(devices)
        for unit in units:
            if not 0 <= unit <= 0xFF:
                raise ValueError(f"unit id {unit} outside 0..255")
        if direct_unit and len(units) == 1 and DIRECT_UNIT not in units:
            units[DIRECT_UNIT] = next(iter(units.values()))
        self._units = units
        self._faults: dict[int, UnitFaults] = {}
        for unit, device in units.items():  # an alias shares its device's faults
            first = next(u for u, d in units.items() if d is device)
            self._faults[unit] = self._faults.get(first) or UnitFaults()
        self._counters = _TcpCounters()
        self._transports: set[asyncio.Transport] = set()

    @property
    def units(self) -> Mapping[int, SimulatedDevice]:
        """Every unit id served (0xFF included when it is the direct alias)."""
        return self._units

    def faults(self, unit: int) -> UnitFaults:
        """The injected faults of ``unit`` (shared with its alias)."""
        return self._faults[unit]

    def stats(self) -> TcpSlaveStats:
        """Counters so far."""
        c = self._counters
        return TcpSlaveStats(
            c.connections,
            c.requests,
            c.responses,
            c.unknown_units,
            c.silent_drops,
            c.bad_headers,
            c.max_in_flight,
        )

    def answer(self, frame: MbapFrame, connection: _SlaveConnection) -> bytes | None:
        """The answer ADU to write now, or None (silent, or sent later)."""
        counters = self._counters
        counters.requests += 1
        tid, unit, pdu = frame
        device = self._units.get(unit)
        if device is None:
            counters.unknown_units += 1
            function = pdu[0] if pdu else 0
            return encode_mbap(
                tid, unit, exception_pdu(function, ExceptionCode.GATEWAY_TARGET_FAILED)
            )
        faults = self._faults[unit]
        if faults.silent:
            counters.silent_drops += 1
            return None
        response = device.handle(pdu)
        if response is None:
            return None
        adu = encode_mbap(tid, unit, response)
        if faults.reply_delay > 0:
            connection.send_later(faults.reply_delay, adu)
            return None
        return adu

    def protocol_factory(self) -> Callable[[], asyncio.Protocol]:
        """For ``loop.create_server``."""
        return lambda: _SlaveConnection(self)

    async def listen(
        self, host: str = "127.0.0.1", port: int = 0, *, ssl: ssl_module.SSLContext | None = None
    ) -> asyncio.Server:
        """Start serving on the running loop; the caller closes the returned server."""
        loop = asyncio.get_running_loop()
        return await loop.create_server(
            self.protocol_factory(), host, port, ssl=ssl, reuse_address=True
        )

    def drop_connections(self) -> None:
        """Abort every open connection (a slave that restarts); the listener stays."""
        for transport in list(self._transports):
            transport.abort()


class SimulatedTcpSlave(TcpSlaveServer):
    """A ``TcpSlaveServer`` on its own loop in a daemon thread: ``start``, ``address``, ``stop``.

    ``port=0`` picks a free port; ``address`` tells which once started.
    """

    def __init__(
        self,
        devices: Mapping[int, SimulatedDevice],
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        ssl: ssl_module.SSLContext | None = None,
        direct_unit: bool = True,
    ) -> None:
        super().__init__(devices, direct_unit=direct_unit)
        self._host = host
        self._port = port
        self._ssl = ssl
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.Server | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._address: tuple[str, int] | None = None

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) served on."""
        if self._address is None:
            raise RuntimeError("not started")
        return self._address

    @property
    def host_port(self) -> str:
        """``HOST:PORT`` as the gateway's ``address`` key and ``--modbus-tcp`` take it."""
        host, port = self.address
        return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    def start(self) -> None:
        """Bind and serve; returns once listening (raises ``OSError`` if it cannot bind)."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(target=self._run, name="sim-modbus-tcp", daemon=True)
        self._thread.start()
        if not self._ready.wait(_START_TIMEOUT_S):
            raise RuntimeError("simulated Modbus TCP slave did not start")
        if self._error is not None:
            self._thread.join(_JOIN_TIMEOUT_S)
            self._thread = None
            raise self._error

    def _run(self) -> None:
        loop = _new_loop()
        self._loop = loop
        try:
            try:
                server = loop.run_until_complete(self.listen(self._host, self._port, ssl=self._ssl))
            except BaseException as error:
                self._error = error
                return
            self._server = server
            sockname = server.sockets[0].getsockname()
            self._address = (sockname[0], sockname[1])
            self._ready.set()
            loop.run_forever()
            server.close()
            self.drop_connections()
            with contextlib.suppress(Exception):
                loop.run_until_complete(server.wait_closed())
        finally:
            self._ready.set()
            loop.close()

    def stop(self) -> None:
        """Stop serving and close every connection."""
        thread, loop = self._thread, self._loop
        if thread is None or loop is None:
            return
        self._thread = None
        with contextlib.suppress(RuntimeError):  # the loop already closed
            loop.call_soon_threadsafe(loop.stop)
        thread.join(_JOIN_TIMEOUT_S)

    def __enter__(self) -> SimulatedTcpSlave:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()
