"""The logged frame trace for commissioning: every request and reply of the masters, decoded.

Every listener holds one ``FrameTrace`` (``gateway.io.frame_trace``) and hands it
each frame; ``Tracer``, the ``--trace`` logging, is one of its subscribers. Lines go
to the ``gateway.trace`` logger at INFO, so they follow the log format (JSON lines
carry every field separately) and never need a second output to be configured.

A reply line shows the latency from the request's arrival, looked up by
(master, transaction id, unit) in a bounded table: a master that leaves
without its answers cannot make the table grow.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection

from .core import pdu as fc
from .core.outcome import Outcome
from .io.frame_trace import reply_outcome

#: Requests remembered for their reply's latency; the oldest are forgotten past this.
MAX_PENDING = 4096


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
