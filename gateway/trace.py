"""The live frame trace for commissioning: every request and reply of the masters, decoded.

Every listener is given one ``FrameTrace`` when it is built and keeps it: the
trace forwards each frame to its subscribers (the ``--trace`` logging ``Tracer``,
the live trace hub while somebody watches), so tracing starts and stops by
subscribing, never by swapping what a listener holds. With no subscriber the
trace is not ``active`` and a frame costs the listener one attribute test.
Lines go to the ``gateway.trace`` logger at INFO, so they follow the log format
(JSON lines carry every field separately) and never need a second output to be
configured.

A reply line shows the latency from the request's arrival, looked up by
(master, transaction id, unit) in a bounded table: a master that leaves
without its answers cannot make the table grow.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection
from typing import Protocol

from .core import pdu as fc
from .core.errors import ExceptionCode
from .core.outcome import Outcome

#: Requests remembered for their reply's latency; the oldest are forgotten past this.
MAX_PENDING = 4096

#: Outcome of a reply whose caller does not name one, by the exception code it carries.
_OUTCOME_BY_CODE: dict[int, Outcome] = {
    ExceptionCode.GATEWAY_PATH_UNAVAILABLE: Outcome.NO_ROUTE,
    ExceptionCode.GATEWAY_TARGET_FAILED: Outcome.TARGET_FAILED,
}


def reply_outcome(pdu: bytes) -> Outcome:
    """What a reply says of its request when the caller does not say: read off the PDU.

    No PDU is a broadcast's; the gateway's own 0x0A and 0x0B name theirs; any other
    exception is taken as the slave's.
    """
    if not pdu:
        return Outcome.BROADCAST
    if not fc.is_exception(pdu):
        return Outcome.OK
    return _OUTCOME_BY_CODE.get(pdu[1] if len(pdu) > 1 else 0, Outcome.SLAVE_EXCEPTION)


def parse_function(text: str) -> int:
    """A function code from ``3``, ``0x03`` or ``read_holding_registers``; ValueError if none."""
    name = text.strip().lower()
    for code, known in fc.FUNCTION_NAMES.items():
        if known == name:
            return code
    try:
        code = int(name, 0)
    except ValueError:
        raise ValueError(
            f"{text!r} is not a function code (1..127) or a name like read_holding_registers"
        ) from None
    if not 1 <= code <= 127:
        raise ValueError(f"function code {code} outside 1..127")
    return code


class FrameTracer(Protocol):
    """What the TCP server calls per frame while tracing: the logger, or the live trace hub."""

    def request(
        self,
        peer: str,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        listener: str | None = None,
        role: str | None = None,
    ) -> None:
        """A request arrived from ``peer`` on ``listener`` (``role``: TLS only)."""

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        """A reply is going out to ``peer`` (``outcome``: see ``reply_outcome`` when None)."""

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        """The answer to a request came after its master had left."""


class FrameTrace:
    """The one frame trace every listener holds: hands each frame to its subscribers.

    Built once with the gateway and given to each listener as it is built; who watches
    changes by ``subscribe`` and ``unsubscribe``, so nothing a listener holds is swapped.
    A listener calls it only while ``active`` (somebody subscribed): a gateway nobody
    traces pays one attribute test per frame.
    """

    __slots__ = ("_subscribers", "active")

    def __init__(self, *subscribers: FrameTracer) -> None:
        self._subscribers: tuple[FrameTracer, ...] = ()
        self.active = False  #: True while somebody subscribed
        for tracer in subscribers:
            self.subscribe(tracer)

    @property
    def subscribers(self) -> tuple[FrameTracer, ...]:
        """Who receives the frames now, in the order they subscribed."""
        return self._subscribers

    def subscribe(self, tracer: FrameTracer) -> None:
        """Send every following frame to ``tracer`` too (once, however often it subscribes)."""
        if tracer not in self._subscribers:
            self._subscribers = (*self._subscribers, tracer)
        self.active = True

    def unsubscribe(self, tracer: FrameTracer) -> None:
        """Stop sending frames to ``tracer`` (nothing if it was not subscribed)."""
        self._subscribers = tuple(s for s in self._subscribers if s is not tracer)
        self.active = bool(self._subscribers)

    def request(
        self,
        peer: str,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        listener: str | None = None,
        role: str | None = None,
    ) -> None:
        """A request arrived from ``peer``: every subscriber hears of it."""
        for tracer in self._subscribers:
            tracer.request(peer, transaction_id, unit, pdu, listener, role)

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        """A reply is going out to ``peer``: every subscriber hears of it."""
        for tracer in self._subscribers:
            tracer.reply(peer, transaction_id, unit, pdu, outcome)

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        """An answer found its master gone: every subscriber hears of it."""
        for tracer in self._subscribers:
            tracer.dropped(peer, transaction_id, unit, function)


class Tracer:
    """Writes one decoded line per frame to and from the masters, optionally filtered."""

    def __init__(
        self,
        units: Collection[int] = (),
        functions: Collection[int] = (),
        logger: logging.Logger | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.units = frozenset(units)
        self.functions = frozenset(functions)
        self._log = logger if logger is not None else logging.getLogger("gateway.trace")
        if self._log.level == logging.NOTSET or self._log.level > logging.INFO:
            # Asking for a trace means wanting it, whatever the general log level.
            self._log.setLevel(logging.INFO)
        self._clock = clock
        self._pending: dict[tuple[str, int, int], float] = {}

    def wants(self, unit: int, function: int) -> bool:
        """True when the filters let a frame for ``unit`` and ``function`` through."""
        return (not self.units or unit in self.units) and (
            not self.functions or (function & 0x7F) in self.functions
        )

    def request(
        self,
        peer: str,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        listener: str | None = None,
        role: str | None = None,
    ) -> None:
        """A request arrived from ``peer`` on ``listener``; ``role`` on TLS listeners only."""
        function = pdu[0] if pdu else 0
        if not self.wants(unit, function):
            return
        pending = self._pending
        if len(pending) >= MAX_PENDING:
            del pending[next(iter(pending))]
        pending[(peer, transaction_id, unit)] = self._clock()
        name = fc.function_name(function)
        detail = fc.describe_request(pdu)
        where = ""
        if listener is not None:
            where = f" via {listener}" if role is None else f" via {listener} role={role}"
        self._log.info(
            "-> %s tid=%d unit=%d %s(%d) %s%s",
            peer,
            transaction_id,
            unit,
            name,
            function,
            detail,
            where,
            extra={
                "direction": "request",
                "peer": peer,
                "transaction_id": transaction_id,
                "unit": unit,
                "function": name,
                "function_code": function,
                "detail": detail,
                "listener": listener,
                "role": role,
            },
        )

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        """A reply is going out to ``peer``; ``outcome`` as in the request metric when known."""
        function = pdu[0] & 0x7F if pdu else 0
        if not self.wants(unit, function):
            return
        latency_ms = self._latency_ms(peer, transaction_id, unit)
        if outcome is None:
            outcome = reply_outcome(pdu)
        name = fc.function_name(function)
        if function in fc.ECHOED_WRITES and not fc.is_exception(pdu):
            detail = fc.describe_request(pdu)  # an echo: address, then value or quantity
        else:
            detail = fc.describe_response(pdu)
        latency = "" if latency_ms is None else f" {latency_ms:.2f} ms"
        self._log.info(
            "<- %s tid=%d unit=%d %s(%d) %s %s%s",
            peer,
            transaction_id,
            unit,
            name,
            function,
            detail,
            outcome,
            latency,
            extra={
                "direction": "reply",
                "peer": peer,
                "transaction_id": transaction_id,
                "unit": unit,
                "function": name,
                "function_code": function,
                "detail": detail,
                "outcome": outcome,
                "latency_ms": latency_ms,
            },
        )

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        """The answer to a request came after its master had left: nothing goes out."""
        if not self.wants(unit, function):
            return
        latency_ms = self._latency_ms(peer, transaction_id, unit)
        name = fc.function_name(function)
        self._log.info(
            "x  %s tid=%d unit=%d %s(%d) dropped: the master left",
            peer,
            transaction_id,
            unit,
            name,
            function,
            extra={
                "direction": "none",
                "peer": peer,
                "transaction_id": transaction_id,
                "unit": unit,
                "function": name,
                "function_code": function,
                "outcome": Outcome.DROPPED,
                "latency_ms": latency_ms,
            },
        )

    def _latency_ms(self, peer: str, transaction_id: int, unit: int) -> float | None:
        """Milliseconds since the request arrived (``None`` if it was not traced)."""
        arrived = self._pending.pop((peer, transaction_id, unit), None)
        return None if arrived is None else (self._clock() - arrived) * 1000.0
