"""One harness for the line core's tests: a core driven as the driver drives it.

``LineHarness`` submits requests, hands the core's answers back (``flush``: what the
driver's pump does), feeds it bytes and timer events with literal times and keeps what
it decided: the frames it wrote, the answers it delivered (by request, each once), its
notes. The unit tests' ``Line`` classes build a core for their line (serial, pipelined)
and add what is their own; the stateful tests build their cores with ``new_core``
(their machine keeps its own pump: it checks every action as it is taken).

Importable by any test module (``tests/`` is on the path beside ``conftest.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any

from gateway.config import LineConfig
from gateway.core.framing import RTU, Framing
from gateway.core.line import LineCore, LineRequest, Note, new_line_core
from gateway.core.outcome import LineEvent, Outcome

Reply = Callable[[bytes, Outcome], None]


def new_core(
    config: LineConfig, now: float, framing: Framing = RTU, max_in_flight: int = 1
) -> LineCore:
    """The core a driver builds for ``config`` (pipelined past one request in flight)."""
    return new_line_core(config, now, None, framing, max_in_flight)


def reply_recorder(answers: dict[int, list[tuple[bytes, str]]], index: int) -> Reply:
    """A reply callback that keeps every answer given to request ``index``."""

    def reply(answer: bytes, outcome: str) -> None:
        answers.setdefault(index, []).append((answer, outcome))

    return reply


class LineHarness:
    """A core, the requests submitted to it and the answers it delivered."""

    def __init__(self, core: LineCore, opened_at: float = -1.0) -> None:
        self.core = core
        self.core.port_opened(opened_at)  # quiet since long before the tests' times
        self.answers: dict[int, list[tuple[bytes, str]]] = {}
        self.requests: list[LineRequest] = []

    def submit(self, slave: int, pdu: bytes, now: float, master: Hashable = "m") -> LineRequest:
        """Submit a request (unit 0: a broadcast) at ``now`` and hand back what is answered."""
        reply = reply_recorder(self.answers, len(self.requests))
        request = LineRequest(slave, pdu, master, reply, broadcast=slave == 0)
        self.requests.append(request)
        self.core.submit(request, now)
        self.flush()
        return request

    def flush(self) -> None:
        """Hand answers back (what the driver's pump does)."""
        deliveries, self.core.deliveries = self.core.deliveries, []
        for delivery in deliveries:
            delivery.request.reply(delivery.pdu, delivery.outcome)

    def frames(self) -> list[bytes]:
        """The frames written since the last call."""
        frames = [transmit.frame for transmit in self.core.transmits]
        self.core.transmits.clear()
        return frames

    def receive(self, data: bytes, now: float) -> None:
        self.core.receive(data, now)
        self.flush()

    def timer(self, now: float | None = None) -> float:
        """Fire the core's timer (at its own deadline unless ``now`` is given)."""
        deadline = self.core.get_timer()
        assert deadline is not None
        at = deadline if now is None else now
        self.core.handle_timer(at)
        self.flush()
        return at

    def answer_of(self, request: LineRequest) -> tuple[bytes, str]:
        """The one answer ``request`` got."""
        got = self.answers[self.requests.index(request)]
        assert len(got) == 1, got
        return got[0]

    def unanswered(self) -> list[LineRequest]:
        return [r for i, r in enumerate(self.requests) if i not in self.answers]

    def notes(self, event: LineEvent) -> list[Any]:
        found: list[Note] = [note for note in self.core.notes if note.event is event]
        return found

    def discarded(self) -> list[str]:
        """The reasons of the discards noted so far."""
        return [n.detail for n in self.core.notes if n.event is LineEvent.DISCARDED]
