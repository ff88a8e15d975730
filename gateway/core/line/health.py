"""Slave health and the probe lane: who is up, suspect or down, and their share of time.

Theory of operation. A timeout counts against a slave only for a function it has
answered before (or when it never answered anything), so a master sending a code the
slave ignores cannot isolate it. After a counted timeout the slave is *suspect*; after
``dead_after`` counted timeouts in a row it is *down*, probed once per back-off
interval (doubling up to ``probe_max_interval``). Requests for suspect and down slaves
wait in the *lane*, one per slave, and share ``probe_share`` of the line's time: a
credit banked at that rate (at most one second's share) pays for their wire time.

*Absent* slaves missed their first contact and never answered anything. While there
are any, a first contact with another slave never heard from is a probe too: it holds
the line for ``initial_timeout``, most likely for nothing (a scan, a stale address
list). It waits in the lane, goes on the lane's credit, and goes free (the lane's
credit in debt) only after the line and the request stayed quiet
``FIRST_CONTACT_QUIET_S``, or, while a master that used the line less is polling (it was
answered within twice the probe's hold), as long as the probe would hold the line (its
longest attempt): a lighter master polling a live slave more often than that is never
held behind a free probe, and one polling less often meets at most one per poll. The
absent addresses cost the masters that ask them, not the others; a light master's own
first contact still goes after the short quiet. After any probe, a master's request that
may go goes before the share's next one (``LineCore._pick``): a poll meets one probe, not
two in a row. Among first contacts, the lightest
master's goes first, then the slave asked for longest; it waits in the lane until the
next free chance has passed (the quiet before it and the probe's longest hold), then is
answered 0x0B unsent.

These parts answer questions and keep counts; the machine (``machine.LineCore``)
makes the transitions and emits the notes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from ..outcome import SlaveState
from .records import INFINITY, LinePolicy, LineRequest

#: A first contact with a slave never heard from, while others are absent, goes without
#: the lane's credit only after the line stayed quiet this long (see the module doc).
FIRST_CONTACT_QUIET_S: Final = 0.1


@dataclass(slots=True)
class SlaveRecord:
    """What the line knows of one slave address."""

    state: SlaveState = SlaveState.UP
    misses: int = 0  # counted timeouts in a row
    answered: set[int] = field(default_factory=set)  # functions it has answered
    backoff: float = 0.0
    next_probe_at: float = 0.0
    known_read: bytes | None = None  # the last read it answered normally (a proof read)


class SlaveHealth:
    """Every slave the line has heard from or given up on."""

    def __init__(self) -> None:
        self.slaves: dict[int, SlaveRecord] = {}
        #: Slaves that missed their first contact and never answered, while not up.
        self.absent: set[int] = set()

    def unheard(self, slave: int) -> bool:
        """True for a slave that has never answered anything."""
        record = self.slaves.get(slave)
        return record is None or not record.answered

    def record(self, slave: int) -> SlaveRecord:
        """What the line knows of ``slave``, created on first need."""
        record = self.slaves.get(slave)
        if record is None:
            record = self.slaves[slave] = SlaveRecord()
        return record

    def state(self, slave: int) -> SlaveState:
        record = self.slaves.get(slave)
        return record.state if record is not None else SlaveState.UP

    def states(self) -> dict[int, SlaveState]:
        return {slave: record.state for slave, record in self.slaves.items()}

    def not_up(self) -> list[tuple[int, SlaveRecord]]:
        return [(s, r) for s, r in self.slaves.items() if r.state is not SlaveState.UP]

    @staticmethod
    def refused_at_once(record: SlaveRecord, now: float) -> bool:
        """True for a down slave whose next probe is not due yet."""
        return record.state is SlaveState.DOWN and now < record.next_probe_at

    @staticmethod
    def count_timeout(
        record: SlaveRecord, function: int, now: float, policy: LinePolicy
    ) -> SlaveState | None:
        """Count a timeout against the slave's health, unless it may just ignore the code;
        the state it moves to, if it changes."""
        if policy.dead_after <= 0:
            return None
        if record.answered and function not in record.answered:
            return None  # a code it never answered: it may ignore it, no sign of death
        record.misses += 1
        if record.state is SlaveState.DOWN:
            record.backoff = min(record.backoff * 2, policy.probe_max_interval)
            record.next_probe_at = now + record.backoff
        elif record.misses >= policy.dead_after:
            record.backoff = policy.probe_interval
            record.next_probe_at = now + record.backoff
            return SlaveState.DOWN
        elif record.state is SlaveState.UP:
            return SlaveState.SUSPECT
        return None


class ProbeLane:
    """One waiting request per suspect or down slave, and their banked share of time."""

    def __init__(self, now: float) -> None:
        self.requests: dict[int, LineRequest] = {}
        self.credit = 0.0
        self.credit_at = now
        self.share = 0.0
        self.cap = 0.0
        #: Slaves whose waiting request is a first contact (see the module doc).
        self.first_contacts: set[int] = set()
        #: Slave -> since when a first contact with it has been waiting (until one goes).
        self.asked_since: dict[int, float] = {}
        self.last_loss = -INFINITY  # when the last attempt ended without an answer

    def configure(self, share: float) -> None:
        self.share = share
        self.cap = share  # at most one second's share banked

    def put(self, request: LineRequest, deadline: float, first_contact: bool = False) -> None:
        """Wait here: one attempt, answered 0x0B if not sent by ``deadline``."""
        request.single = True
        request.lane_deadline = deadline
        self.requests[request.slave] = request
        if first_contact:
            self.first_contacts.add(request.slave)
            self.asked_since.setdefault(request.slave, request.enqueued_at)

    def remove(self, request: LineRequest) -> None:
        del self.requests[request.slave]
        self.first_contacts.discard(request.slave)
        request.lane_deadline = INFINITY

    def free_at(self, quiet_since: float, request: LineRequest, hold: float) -> float:
        """When the first contact ``request`` may go without the lane's credit: the line
        and the request itself quiet as long as it would ``hold`` the line, at least
        ``FIRST_CONTACT_QUIET_S`` (so the masters that ask in the same moment compete for
        it, not the first to ask, and a master polling more often is not held behind it)."""
        quiet = hold if hold > FIRST_CONTACT_QUIET_S else FIRST_CONTACT_QUIET_S
        return max(quiet_since, self.last_loss, request.enqueued_at) + quiet

    def holds(self, request: LineRequest) -> bool:
        return self.requests.get(request.slave) is request

    def candidate(
        self,
        may_go: Callable[[LineRequest], bool],
        account: Callable[[LineRequest], float] | None = None,
    ) -> LineRequest | None:
        """The oldest request ``may_go`` lets go (``take`` takes it). With ``account`` (its
        master's wire time used), first contacts go after isolated slaves' requests, the
        lightest master's first (masters whose first contacts went unanswered paid for
        them), then the slave asked for longest (a master polling a new slave asks it
        again and again, a scan asks each address once)."""
        best: LineRequest | None = None
        best_key = (0.0, 0.0, 0.0)
        first = self.first_contacts
        since = self.asked_since
        for request in self.requests.values():
            if not may_go(request):
                continue
            enqueued = request.enqueued_at
            if account is not None and request.slave in first:
                key = (account(request), since.get(request.slave, enqueued), enqueued)
            else:
                key = (0.0, enqueued, enqueued)
            if best is None or key < best_key:
                best, best_key = request, key
        return best

    def take(self, request: LineRequest) -> None:
        """``request`` goes: out of the lane, its slave no longer waiting for a first contact."""
        self.remove(request)
        self.asked_since.pop(request.slave, None)

    def expired(self, now: float) -> list[LineRequest]:
        return [r for r in self.requests.values() if now >= r.lane_deadline]

    def earliest(self) -> float:
        when = INFINITY
        for request in self.requests.values():
            when = min(when, request.lane_deadline)
        return when

    def credit_now(self, now: float) -> float:
        """The lane's share of line time banked so far (negative: in debt)."""
        if now > self.credit_at:
            banked = self.credit + self.share * (now - self.credit_at)
            if banked > -1e-9:  # paid off: rounding must not leave a debt too small to wait for
                banked = max(banked, 0.0)
            self.credit = min(banked, self.cap)
            self.credit_at = now
        return self.credit

    def spend(self, wire: float, now: float) -> None:
        """Pay ``wire`` seconds from the share."""
        self.credit_now(now)
        self.credit -= wire

    def credit_time(self) -> float:
        """When the banked share reaches zero again."""
        if self.credit >= 0.0:
            return self.credit_at
        if self.share <= 0.0:
            return INFINITY
        return self.credit_at - self.credit / self.share
