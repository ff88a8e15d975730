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
from gateway.core.line import LineCore, LineRequest, Note, Transmit, new_line_core
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


class SimulatedTime:
    """Literal time for a core and what happens around it: ``at`` schedules an act,
    ``run`` fires the core's timer and the acts in time order until ``end``, pumping the
    core's actions after each (``_pump``: the subclass's driver)."""

    core: LineCore

    def __init__(self) -> None:
        import heapq

        self._heap = heapq
        self.now = 0.0
        self._events: list[tuple[float, int, Callable[[], object]]] = []
        self._seq = 0

    def at(self, when: float, act: Callable[[], object]) -> None:
        self._seq += 1
        self._heap.heappush(self._events, (when, self._seq, act))

    def run(self, end: float) -> None:
        while True:
            timer = self.core.get_timer()
            event_at = self._events[0][0] if self._events else end + 1.0
            if timer is not None and timer <= event_at and timer <= end:
                self.now = max(self.now, timer)
                self.core.handle_timer(self.now)
            elif event_at <= end:
                _, _, act = self._heap.heappop(self._events)
                self.now = max(self.now, event_at)
                act()
            else:
                self.now = end
                return
            self._pump()

    def _pump(self) -> None:
        raise NotImplementedError


class DeafWhileBusyLine(SimulatedTime):
    """A core on a simulated serial line of single-threaded slaves, with literal times.

    Each slave answers a request ``turnaround(slave, pdu, now)`` seconds after the
    request's end (``None``: never). While it works it is deaf, as a device with one thread
    is; or (``deaf=False``) it keeps what it heard and answers each in turn, as a device
    with a receive buffer does. Its answer carries the data of the request it answers
    (register ``a`` holds ``a``), so an answer delivered to another request is seen.
    Masters are closed loops or periodic: ``run`` drives time until ``end``.
    """

    def __init__(
        self,
        core: LineCore,
        char: float,
        turnaround: Callable[[int, bytes, float], float | None],
        deaf: bool = True,
    ) -> None:
        super().__init__()
        self.core = core
        self.char = char
        self.turnaround = turnaround
        self.deaf = deaf
        self.busy_until: dict[int, float] = {}
        self.sent: list[bytes] = []  # every frame the core wrote, in order
        self.outcomes: list[tuple[Hashable, LineRequest, Outcome, bytes]] = []
        self.wrong = 0  # answers whose data is another request's
        self.on_answer: Callable[[LineRequest, Outcome], None] = lambda _r, _o: None
        self.on_transmit: Callable[[Transmit], None] = lambda _t: None
        core.port_opened(-1.0)

    def submit(self, master: Hashable, slave: int, pdu: bytes) -> LineRequest:
        request = LineRequest(slave, pdu, master, lambda _pdu, _outcome: None)
        self.core.submit(request, self.now)
        self._pump()
        return request

    def _pump(self) -> None:
        core = self.core
        while core.transmits or core.deliveries:
            transmits, core.transmits = core.transmits, []
            for transmit in transmits:
                self.sent.append(transmit.frame)
                self.on_transmit(transmit)
                self._hear(transmit.frame)
            deliveries, core.deliveries = core.deliveries, []
            for request, pdu, outcome, _wire in deliveries:
                if outcome is Outcome.OK and pdu[0] == 3 and pdu[2:] != _registers(request.pdu):
                    self.wrong += 1
                self.outcomes.append((request.master, request, outcome, pdu))
                self.on_answer(request, outcome)

    def _hear(self, frame: bytes) -> None:
        from gateway.core.rtu import encode_rtu

        slave, pdu = frame[0], frame[1:-2]
        end = self.now + len(frame) * self.char
        busy_until = self.busy_until.get(slave, -1.0)
        if slave == 0 or (self.deaf and busy_until > self.now):
            return  # a broadcast, or deaf: it is still working on an earlier request
        turnaround = self.turnaround(slave, pdu, self.now)
        if turnaround is None:
            return
        answer = encode_rtu(slave, bytes((3, len(_registers(pdu)))) + _registers(pdu))
        arrives = max(end, busy_until) + turnaround + len(answer) * self.char
        self.busy_until[slave] = arrives

        def arrive() -> None:
            self.core.receive(answer, self.now)

        self.at(arrives, arrive)


def _registers(pdu: bytes) -> bytes:
    """The data of an FC 3 read in ``DeafWhileBusyLine``: register ``a`` holds ``a``."""
    address = (pdu[1] << 8) | pdu[2]
    quantity = (pdu[3] << 8) | pdu[4]
    return b"".join(((address + i) & 0xFFFF).to_bytes(2, "big") for i in range(quantity))
