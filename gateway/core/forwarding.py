"""Requests the gateway sends as a Modbus TCP client, and whose turn it is (no I/O, no clock).

Theory of operation. A standby of a redundant pair forwards its masters' requests to the
active gateway's Modbus TCP listener over a few connections (*links*). Two parts of that
are decisions, kept here with ``now`` passed in:

``Flights``: the requests outstanding on one connection. Each is sent under a transaction
id (TID) from the core's ``TransactionIds`` that is neither outstanding nor reserved, has a
deadline, and is matched only by an answer carrying its TID that can answer it (its unit,
its function or function | 0x80, a read's byte count, a write's echo: ``check_identity``,
the rule every line applies). A request given up (``expire``, ``give_up``) keeps its TID
reserved, at most ``lost_kept`` of them, the oldest freed first: ids are handed out in
sequence, so a freed one returns only after 65,536 others. A reserved TID's answer is
``Late`` (dropped); any other frame is ``Stray``: a connection that sends one is out of
step and cannot be trusted any more.

``Rounds``: the requests of several masters that share one link, waiting for a place in
its window. Each master has its own queue (bounded: ``bound`` requests waiting or
outstanding); the link takes the masters in turn, one request each, so a master with many
requests, or many connections behind one address, takes one turn in each round and no
more. A master's requests keep their order.

Invariants: no two outstanding requests share a TID, and no reserved TID is handed out;
an answer reaches only the request whose TID it carries and which it can answer; every
request leaves exactly once (answered, expired, given up or taken at close); a master
never has more than ``bound`` requests waiting or outstanding.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Iterator
from dataclasses import dataclass, field
from typing import Final, Generic, TypeVar

from .errors import ResponseError
from .mbap import MbapFrame, TransactionIds
from .rtu import check_identity

#: TIDs of given-up requests kept reserved per connection by default.
LOST_KEPT: Final = 256
INFINITY: Final = float("inf")

Item = TypeVar("Item")


@dataclass(slots=True, eq=False)
class Flight(Generic[Item]):
    """One request outstanding on the connection: what the caller keeps with it."""

    item: Item
    tid: int
    unit: int
    pdu: bytes
    deadline: float


@dataclass(frozen=True, slots=True)
class Answered(Generic[Item]):
    """The answer to an outstanding request (it is no longer outstanding)."""

    item: Item
    pdu: bytes


@dataclass(frozen=True, slots=True)
class Late:
    """The answer to a request given up; ``expected`` is false where none was awaited (a
    broadcast, a request whose master left): not news either way."""

    expected: bool


@dataclass(frozen=True, slots=True)
class Stray:
    """A frame that answers nothing outstanding or reserved: the stream is out of step."""

    why: str


Match = Answered[Item] | Late | Stray


def mismatch(unit: int, request_pdu: bytes, got_unit: int, pdu: bytes) -> str:
    """Why ``pdu`` from ``got_unit`` cannot answer the request (empty when it can)."""
    if not pdu:
        return "an empty answer"
    try:
        check_identity(unit, request_pdu[0], request_pdu, got_unit, pdu)
    except ResponseError as error:
        return str(error)
    return ""


class Flights(Generic[Item]):
    """The requests outstanding on one client connection (see the module doc)."""

    __slots__ = ("ids", "lost_kept", "outstanding", "reserved")

    def __init__(self, lost_kept: int = LOST_KEPT, ids: TransactionIds | None = None) -> None:
        self.ids = TransactionIds() if ids is None else ids
        self.lost_kept = lost_kept
        self.outstanding: dict[int, Flight[Item]] = {}  #: by TID, in the order sent
        #: TIDs given up -> (unit, request PDU, answer expected), oldest first.
        self.reserved: dict[int, tuple[int, bytes, bool]] = {}

    def __len__(self) -> int:
        return len(self.outstanding)

    def send(self, item: Item, unit: int, pdu: bytes, deadline: float) -> bytes:
        """The ADU of a new outstanding request, under a TID nothing else holds."""
        ids, outstanding, reserved = self.ids, self.outstanding, self.reserved
        frame = ids.encode(unit, pdu)
        for _ in range(0x10000):
            if ids.current not in outstanding and ids.current not in reserved:
                break
            frame = ids.encode(unit, pdu)
        else:  # pragma: no cover - bounded by the callers' windows and ``lost_kept``
            raise RuntimeError("every transaction id is outstanding or reserved")
        outstanding[ids.current] = Flight(item, ids.current, unit, pdu, deadline)
        return frame

    def match(self, frame: MbapFrame) -> Match[Item]:
        """What a frame from the server is: an answer, a late answer or a stray."""
        tid, unit, pdu = frame
        flight = self.outstanding.get(tid)
        if flight is None:
            lost = self.reserved.pop(tid, None)
            if lost is None:
                return Stray(f"transaction id {tid}: not outstanding")
            why = mismatch(lost[0], lost[1], unit, pdu)
            return Stray(f"transaction id {tid}: {why}") if why else Late(lost[2])
        why = mismatch(flight.unit, flight.pdu, unit, pdu)
        if why:
            return Stray(f"transaction id {tid}: {why}")
        del self.outstanding[tid]
        return Answered(flight.item, pdu)

    def get_timer(self) -> float:
        """The earliest deadline of an outstanding request (``INFINITY``: none)."""
        return min((flight.deadline for flight in self.outstanding.values()), default=INFINITY)

    def expire(self, now: float) -> list[Item]:
        """The requests past their deadline at ``now``, given up (their TIDs reserved)."""
        expired = [flight for flight in self.outstanding.values() if flight.deadline <= now]
        for flight in expired:
            self._reserve(flight, expected=True)
        return [flight.item for flight in expired]

    def give_up(self, tid: int, *, expected: bool) -> Item | None:
        """Stop waiting for ``tid``'s answer (its TID reserved); its item, if outstanding."""
        flight = self.outstanding.get(tid)
        if flight is None:
            return None
        self._reserve(flight, expected=expected)
        return flight.item

    def take_all(self) -> list[Item]:
        """Every outstanding request, and no reservation kept: the connection is gone."""
        items = [flight.item for flight in self.outstanding.values()]
        self.outstanding.clear()
        self.reserved.clear()
        return items

    def _reserve(self, flight: Flight[Item], *, expected: bool) -> None:
        del self.outstanding[flight.tid]
        reserved = self.reserved
        reserved[flight.tid] = (flight.unit, flight.pdu, expected)
        if len(reserved) > self.lost_kept:
            del reserved[next(iter(reserved))]  # the oldest: its id returns last in sequence


@dataclass(slots=True, eq=False)
class _Queue(Generic[Item]):
    """One master's waiting requests (oldest first) and its count outstanding."""

    waiting: deque[tuple[Item, float]] = field(default_factory=deque)  #: (item, deadline)
    outstanding: int = 0


class Rounds(Generic[Item]):
    """Several masters' requests waiting for one link, taken in turn (see the module doc)."""

    __slots__ = ("_turns", "bound", "masters")

    def __init__(self, bound: int) -> None:
        self.bound = bound
        self.masters: dict[Hashable, _Queue[Item]] = {}
        self._turns: deque[Hashable] = deque()  #: masters with requests waiting, next first

    def __bool__(self) -> bool:
        return bool(self._turns)

    def held(self, master: Hashable) -> int:
        """Requests of ``master`` waiting or outstanding."""
        queue = self.masters.get(master)
        return 0 if queue is None else len(queue.waiting) + queue.outstanding

    def add(self, master: Hashable, item: Item, deadline: float) -> bool:
        """Queue ``item`` behind ``master``'s others; False when its bound is reached."""
        queue = self.masters.get(master)
        if queue is None:
            queue = self.masters[master] = _Queue()
        if len(queue.waiting) + queue.outstanding >= self.bound:
            return False
        if not queue.waiting:
            self._turns.append(master)
        queue.waiting.append((item, deadline))
        return True

    def next(self) -> tuple[Hashable, Item, float] | None:
        """The next master's oldest request, now outstanding; the master goes to the back."""
        if not self._turns:
            return None
        master = self._turns.popleft()
        queue = self.masters[master]
        item, deadline = queue.waiting.popleft()
        queue.outstanding += 1
        if queue.waiting:
            self._turns.append(master)
        return master, item, deadline

    def done(self, master: Hashable) -> None:
        """One of ``master``'s outstanding requests left (answered, expired, given up)."""
        queue = self.masters.get(master)
        if queue is not None and queue.outstanding:
            queue.outstanding -= 1

    def expire(self, now: float) -> list[Item]:
        """Waiting requests past their deadline (each master's oldest first), removed."""
        expired: list[Item] = []
        for master in list(self._turns):
            waiting = self.masters[master].waiting
            while waiting and waiting[0][1] <= now:
                expired.append(waiting.popleft()[0])
            if not waiting:
                self._turns.remove(master)
        return expired

    def get_timer(self) -> float:
        """The earliest deadline of a waiting request (``INFINITY``: none)."""
        return min((self.masters[master].waiting[0][1] for master in self._turns), default=INFINITY)

    def leave(self, master: Hashable) -> list[Item]:
        """``master`` left: its waiting requests, removed with it."""
        queue = self.masters.pop(master, None)
        if queue is None:
            return []
        if queue.waiting:
            self._turns.remove(master)
        return [item for item, _deadline in queue.waiting]

    def take_all(self) -> list[Item]:
        """Every waiting request, each master's in order; the masters stay known."""
        items: list[Item] = []
        for queue in self.masters.values():
            items.extend(item for item, _deadline in queue.waiting)
            queue.waiting.clear()
            queue.outstanding = 0
        self._turns.clear()
        return items

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self.masters)
