"""The frame trace every listener holds: each request and reply of the masters handed to
whoever subscribed (the ``--trace`` log, the live trace stream).

Every listener is given one ``FrameTrace`` when it is built and keeps it: the
trace forwards each frame to its subscribers, so tracing starts and stops by
subscribing, never by swapping what a listener holds. With no subscriber the
trace is not ``active`` and a frame costs the listener one attribute test.
What a subscriber makes of a frame is its own: ``gateway.trace.Tracer`` logs it,
``io.http.live`` streams it to a browser.
"""

from __future__ import annotations

from typing import Protocol

from ..core import pdu as fc
from ..core.errors import ExceptionCode
from ..core.outcome import Outcome

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
