"""The masters' fair queue and its bounds: whose request goes next, by wire time used.

Theory of operation. Each master has its own queue and an account of the wire time its
transactions took (start-time fair queuing): the master with the smallest virtual time
goes next, and its account is charged with what its transaction actually cost (timeouts
included), so a master provoking timeouts spends its own share. Charges are whole
*turns*: the line's typical answered transaction (its grain) times the number of them a
transaction took, rounded (one shorter than half a turn is charged its own time).
Transactions that differ by a slave's jitter cost the same, so masters served in one
round start the next with equal accounts and go in the order they asked, as first come,
first served would put them, not in the order of that jitter; a timeout or a long read
still costs its many turns. The grain moves only when the typical transaction leaves a
band around it, and a new grain applies from the next round: masters charged in one
round are charged alike. A master that waited while others used the line starts from the
line's virtual clock, never below it (no banked credit). A master with nothing waiting
or on the wire for at least the line's typical transaction goes next after the
transaction on the wire (behind others that came so before it), unless its account is
ahead of every waiting master's by more than a turn: it cannot become the heaviest user
that way. A master answered a moment ago that asks again at once takes its fair turn: it
goes behind the round it left. Each master has its own queue bound (0x06 beyond it); the
line-wide bound pushes out the longest queue's newest request before refusing a master
with a shorter queue. A request still unsent after the line's ``max_queue_wait`` is
overdue: ``arrivals`` holds the queued requests in submission order, so the oldest is
found without a scan (requests that left another way are skipped when met at its head).

This part keeps the order and the counts; it answers questions and never emits an
action: the machine (``machine.LineCore``) decides what becomes of a request.
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Callable, Container, Hashable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Final

from .records import LineRequest, LineStats

#: The weight of the newest transaction in the line's typical one (a moving mean).
TYPICAL_WEIGHT: Final = 1.0 / 16.0
#: The grain follows the typical answered transaction only when that leaves this band
#: around it: a typical transaction, and its jitter, are one turn whatever the grain.
GRAIN_BAND: Final = 1.25
#: The grain never goes below this (seconds): a line whose transactions take next to no
#: time charges them as they took.
GRAIN_FLOOR_S: Final = 0.001
#: A master idle this long (or the round of waiting requests, if shorter) polls now and
#: then: it goes next. One asking again sooner polls flat out: it takes its fair turn.
REST_S: Final = 0.1


@dataclass(slots=True, eq=False)
class Master:
    """One master's queue and its account of wire time (start-time fair queuing)."""

    key: Hashable
    queue: deque[LineRequest] = field(default_factory=deque)
    vtime: float = 0.0
    heap_seq: int = -1  # the sequence number of its live heap entry, -1 when not in the heap
    queued: int = 0  # requests waiting (its queue, the lane, the retry slot)
    gone: bool = False
    #: When its last transaction ended (``None``: never served): see ``enqueue``.
    answered_at: float | None = None


class FairQueue:
    """The masters' queues in start-time fair order, with the line's waiting count."""

    def __init__(self, stats: LineStats) -> None:
        self.stats = stats
        self.masters: dict[Hashable, Master] = {}
        #: Masters by (start time, 0 for the head of the line or 1, sequence): see ``enqueue``.
        self.heap: list[tuple[float, int, int, Master]] = []
        self.seq = 0
        self.vclock = 0.0
        self.vmax = 0.0  # the furthest account of a master that waited (``push``)
        self.queued = 0  # requests waiting for the line, wherever they wait
        #: The line's typical transaction, the silence after it included (a moving mean kept
        #: by ``LineCore._charge``): how long a master must have been idle to go first.
        self.typical = 0.0
        #: What one turn is (``cost``; 0: nothing answered yet): the typical *answered*
        #: transaction, the silence after it included, to within ``GRAIN_BAND``
        #: (``learned``). Timeouts are left out: one would lift it for every master.
        self.grain = 0.0
        #: The turn before the last change, for masters charged from an account up to
        #: ``grain_since`` (the virtual time when it changed): a new turn applies from
        #: the next round, never to part of one.
        self.old_grain = 0.0
        self.grain_since = -1.0
        self._mean = 0.0
        self._mean_square = 0.0
        #: Requests queued by ``enqueue``, oldest first; some may have left since (``overdue``).
        self.arrivals: deque[LineRequest] = deque()

    def master(self, key: Hashable) -> Master:
        """``key``'s account, created on first need."""
        master = self.masters.get(key)
        if master is None:
            master = self.masters[key] = Master(key)
        return master

    def over_master_bound(self, master: Master, on_wire: int, bound: int) -> bool:
        """True when ``master`` already has ``bound`` requests waiting or on the wire."""
        return master.queued + on_wire >= bound

    def push_out(self, master: Master) -> LineRequest | None:
        """The line is full: take the newest request of the longest queue if that is not
        ``master``'s (the caller answers it), else ``None`` (refuse ``master``)."""
        longest = max(self.masters.values(), key=lambda m: len(m.queue), default=None)
        if longest is None or longest is master or len(longest.queue) <= len(master.queue) + 1:
            return None
        victim = longest.queue.pop()
        self.dequeued(longest, victim)
        return victim

    def enqueue(self, master: Master, request: LineRequest, idle: bool, now: float) -> None:
        """Queue ``request``; a master that was ``idle`` (nothing waiting or on the wire)
        as long as the round of waiting requests would take (at most ``REST_S``) goes to the
        head of the fair order, unless its account is ahead of every waiting master's.

        Start times alone would put it behind every master whose start time equals the
        line's virtual time (a whole round of deep queues), and, once served, behind the rest
        of that round: the virtual time moves one transaction per round. Its account is
        still charged, so it takes no more than the heaviest user: past that it waits its
        turn. A master answered a moment ago that asks again at once (a closed loop, its
        network round trip shorter than a transaction) takes its fair turn behind the
        masters that waited meanwhile, as first come, first served would put it, not the
        head of the line round after round. Where a transaction is shorter than the
        masters' round trips (a fast port), every master comes back rested, and the heads
        go in the order they came: first come, first served again.
        """
        master.queue.append(request)
        self.arrivals.append(request)
        master.queued += 1
        self.queued += 1
        self.stats.queue_depth = self.queued
        if master.heap_seq < 0:
            if master.vtime < self.vclock:
                master.vtime = self.vclock
            answered_at = master.answered_at
            # Idle as long as the round it would pass (the waiting requests' typical
            # transactions), up to ``REST_S``: a closed loop's round trip is shorter.
            rest = min(self.queued * self.typical, REST_S)
            rested = answered_at is None or now - answered_at >= rest
            # At most a turn ahead of the heaviest waiting master (the others' charges are
            # rounded to whole turns, its short reads are not), and at most two ahead of
            # the virtual time: rested masters that keep coming cannot keep the others'
            # turn from coming (the virtual time moves on those others' turns only).
            light = (
                master.vtime <= self.vmax + self.grain
                and master.vtime <= self.vclock + 2 * self.typical
            )
            self.push(master, idle and rested and light)

    def went_at_once(self, master: Master, now: float) -> None:
        """``master``'s request found the line free and nothing waiting, and went without
        queuing: the accounts as ``enqueue`` (an idle master) then ``pop`` leave them."""
        vclock = self.vclock
        vtime = master.vtime
        if vtime < vclock:
            master.vtime = vtime = vclock
        answered_at = master.answered_at
        typical = self.typical
        if (
            (answered_at is not None and now - answered_at < min(typical, REST_S))
            or vtime > self.vmax + self.grain
            or vtime > vclock + 2 * typical
        ):
            # Not rested, or not light: it would have gone at its own account (``push``).
            if vtime > self.vmax:
                self.vmax = vtime
            self.vclock = vtime

    def queue_at_front(self, request: LineRequest) -> None:
        """Back from the lane: first, but behind its master's earlier broadcasts."""
        master = self.master(request.master)
        place = 0
        for index, queued in enumerate(master.queue):
            if queued.broadcast and queued.order < request.order:
                place = index + 1
        master.queue.insert(place, request)
        self._arrived(request)
        master.queued += 1
        self.queued += 1
        self.stats.queue_depth = self.queued
        if master.heap_seq < 0:
            self.push(master)

    def _arrived(self, request: LineRequest) -> None:
        """Into ``arrivals`` by the time it was first queued: back from the lane, it is as
        overdue as it was (``max_queue_wait``) and must be found in that order."""
        arrivals = self.arrivals
        at = request.enqueued_at
        place = len(arrivals)
        while place and arrivals[place - 1].enqueued_at > at:
            place -= 1
        arrivals.insert(place, request)

    def count_waiting(self, request: LineRequest, delta: int) -> None:
        """A request enters (+1) or leaves (-1) the waiting set outside its master's queue."""
        master = self.masters.get(request.master)
        if master is not None:
            master.queued += delta
        self.queued += delta
        self.stats.queue_depth = self.queued

    def push(self, master: Master, head: bool = False) -> None:
        """Into the fair order at its account, or (``head``) before every master at the
        line's virtual time, in arrival order."""
        self.seq += 1
        master.heap_seq = self.seq
        if head:
            heapq.heappush(self.heap, (self.vclock, 0, self.seq, master))
            return
        vtime = master.vtime
        if vtime > self.vmax:
            self.vmax = vtime
        heapq.heappush(self.heap, (vtime, 1, self.seq, master))

    def reschedule(self, master: Master) -> None:
        """Put ``master`` back in the fair order after its transaction or a request taken
        from its queue (or forget it). A master whose queue emptied leaves the order: its
        entry goes stale, and its next request enters by ``enqueue``'s rules, not on a
        place taken for a request since gone (a closed loop's read, on the head of the
        line its first request had as a newcomer)."""
        if master.queue:
            if master.heap_seq < 0:
                self.push(master)
            return
        master.heap_seq = -1
        if master.queued == 0 and master.gone:
            self.masters.pop(master.key, None)

    def dequeued(self, master: Master | None, request: LineRequest) -> None:
        if master is not None:
            master.queued -= 1
        self.queued -= 1
        self.stats.queue_depth = self.queued

    def remove(self, request: LineRequest) -> None:
        """Take ``request`` out of its master's queue."""
        owner = self.masters[request.master]
        owner.queue.remove(request)
        self.dequeued(owner, request)
        self.reschedule(owner)

    def pop(
        self, now: float, first_eligible: Callable[[Master, float], LineRequest | None]
    ) -> tuple[LineRequest, Master] | None:
        """The fairest master's first request that may go now (``first_eligible`` says
        which), taken from its queue; masters with nothing eligible keep their place."""
        heap = self.heap
        skipped: list[tuple[Master, bool]] = []
        chosen: tuple[LineRequest, Master] | None = None
        while heap:
            vtime, rank, seq, master = heapq.heappop(heap)
            if master.heap_seq != seq:
                continue  # stale entry
            if rank == 0 and len(master.queue) > 1:
                self.push(master)  # no longer a single request: its fair turn
                continue
            master.heap_seq = -1
            request = first_eligible(master, now)
            if request is None:
                if master.queue:
                    skipped.append((master, rank == 0))
                continue
            master.queue.remove(request)
            arrivals = self.arrivals
            if arrivals and arrivals[0] is request:
                arrivals.popleft()  # the usual case: the oldest goes first
            master.queued -= 1  # ``dequeued``
            self.queued -= 1
            self.stats.queue_depth = self.queued
            if vtime > self.vclock:
                self.vclock = vtime
            chosen = request, master
            break
        for master, head in skipped:
            self.push(master, head)
        return chosen

    def answered(self, requests: Iterable[LineRequest], now: float) -> None:
        """``requests`` (reads that joined another) were answered at ``now``: their masters
        were answered as much as by a transaction of their own (``enqueue``'s rest)."""
        for request in requests:
            master = self.masters.get(request.master)
            if master is not None:
                master.answered_at = now

    def learned(self, wire: float) -> None:
        """An answered transaction took ``wire`` seconds, the silence after it included.

        The typical one is the transaction a moment of the line's time falls in (the mean
        weighted by time: moving means of the times and of their squares), not the mean
        transaction: on a line of long reads beside a master's short polls, the mean falls
        between the two, and the long reads, near one and a half of it, would be rounded to
        one turn or two by their jitter."""
        if wire <= 0.0:
            return  # nothing held the line (an answer taken in the instant it was sent)
        mean = self._mean
        if mean > 0.0:
            mean += (wire - mean) * TYPICAL_WEIGHT
            self._mean_square += (wire * wire - self._mean_square) * TYPICAL_WEIGHT
        else:
            mean = wire  # the first: from there, not climbing from zero
            self._mean_square = wire * wire
        self._mean = mean
        typical = self._mean_square / mean
        grain = self.grain
        if not grain * (1.0 / GRAIN_BAND) <= typical <= grain * GRAIN_BAND:
            if self.vclock > self.grain_since:  # the first change in this round
                self.old_grain = grain
                self.grain_since = self.vclock
            self.grain = typical if typical > GRAIN_FLOOR_S else GRAIN_FLOOR_S

    def cost(self, wire: float, start: float) -> float:
        """``wire`` seconds, charged from the account ``start``, in whole turns
        (``learned``), or as they are when shorter than half a turn (or before the line
        knows what a turn is). A master charged in the round the turn changed in is
        charged the round's turn: masters served from one account end with one account.
        (The first turn applies at once: before it, transactions were charged as they
        took, and turns that were never charged cannot be told apart.)"""
        grain = self.grain
        if start <= self.grain_since and self.old_grain:
            grain = self.old_grain
        turns = round(wire / grain) if grain else 0
        if turns:
            return turns * grain
        # To the nanosecond: transactions that took the same time cost the same, not costs
        # a rounding error apart. (``round(x, 9)`` would go through a decimal string.)
        return round(wire * 1e9) / 1e9

    def charge(self, master: Master, wire: float, charged: float) -> None:
        """``master``'s transaction took ``wire`` seconds, of which ``charged`` were charged
        when it was sent (an estimate, on a pipelined line)."""
        if charged:
            master.vtime += self.cost(wire, master.vtime - charged) - charged
        else:
            # Masters charged alike from one account have the same account: they go in the
            # order they asked (``push``), not in the order of their transactions' jitter.
            account = self.vclock if master.vtime < self.vclock else master.vtime
            master.vtime = account + self.cost(wire, account)
        if master.heap_seq >= 0:
            self.push(master)  # its old entry goes stale

    def charge_ahead(self, master: Master, amount: float) -> None:
        """Charge ``amount`` now (a broadcast's turnaround, a pipelined send's estimate)."""
        master.vtime = max(master.vtime, self.vclock) + amount

    def isolated(self, slave: int) -> list[LineRequest]:
        """Take every waiting request for ``slave`` from the queues, oldest first."""
        doomed: list[tuple[Master, LineRequest]] = []
        for master in self.masters.values():
            for request in master.queue:
                if request.slave == slave and not request.broadcast:
                    doomed.append((master, request))
        doomed.sort(key=lambda pair: pair[1].enqueued_at)
        for master, request in doomed:
            master.queue.remove(request)
            self.dequeued(master, request)
            self.reschedule(master)
        return [request for _, request in doomed]

    def first_contacts(
        self, unheard: Callable[[int], bool], skip: Container[int]
    ) -> list[LineRequest]:
        """Take from the queues the oldest request for each slave ``unheard`` names and
        ``skip`` does not (the caller puts them in the lane), oldest first. A request its
        master has sent more requests to that slave after stays queued: moved to the lane,
        it would be passed by them (a read before the write it follows, or the reverse)."""
        found: list[tuple[Master, LineRequest]] = []
        for master in self.masters.values():
            for request in master.queue:
                if not request.broadcast and request.slave not in skip and unheard(request.slave):
                    found.append((master, request))
        found.sort(key=lambda pair: pair[1].enqueued_at)
        taken: list[LineRequest] = []
        slaves: set[int] = set()
        for master, request in found:
            if request.slave in slaves:
                continue
            slaves.add(request.slave)
            if self.followed(master, request):
                continue
            master.queue.remove(request)
            self.dequeued(master, request)
            self.reschedule(master)
            taken.append(request)
        return taken

    @staticmethod
    def followed(master: Master, request: LineRequest) -> bool:
        """``master`` has another request queued for ``request``'s slave."""
        slave = request.slave
        return any(other.slave == slave and other is not request for other in master.queue)

    def overdue(self, queued_before: float) -> list[LineRequest]:
        """Take from the queues every request still unsent that was queued before
        ``queued_before`` (the caller answers them); forget those that left otherwise."""
        arrivals = self.arrivals
        taken: list[LineRequest] = []
        while arrivals and arrivals[0].enqueued_at < queued_before:
            request = arrivals.popleft()
            if request.sent or request.answered:
                continue
            owner = self.masters.get(request.master)
            if owner is None or request not in owner.queue:
                continue  # in the lane, or handed on: it has its own deadline
            owner.queue.remove(request)
            self.dequeued(owner, request)
            self.reschedule(owner)
            taken.append(request)
        return taken

    def waiting(self) -> Iterator[LineRequest]:
        """Every request in the masters' queues."""
        for master in self.masters.values():
            yield from master.queue

    def take_all(self) -> list[LineRequest]:
        """Empty every queue (the caller takes the lane and the retries with it)."""
        taken: list[LineRequest] = []
        for master in self.masters.values():
            taken.extend(master.queue)
            master.queue.clear()
            master.queued = 0
            master.heap_seq = -1
        self.heap.clear()
        self.arrivals.clear()
        self.masters = {k: m for k, m in self.masters.items() if not m.gone}
        self.queued = 0
        self.stats.queue_depth = 0
        return taken
