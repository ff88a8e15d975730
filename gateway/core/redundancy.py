"""The redundancy role: which gateway of an active/standby pair may drive the bus.

Theory of operation (docs/redundancy.md gives the long form and the proof). RS-485 has
no arbitration, so exactly one gateway of a pair may transmit: the *active*, and only
while it holds a *lease*. The machine is pure and speaks the line core's contract:
every input carries ``now`` (seconds on one clock that counts suspend, CLOCK_BOOTTIME in
the shell), ``get_timer()`` says when ``handle_timer(now)`` must next run, and what the
shell is to do comes out as actions: ``changes`` (set every line to the new role) and
``keepalives`` (read one register on each idle line). Nothing here reads a clock or does
I/O; the lease check (``may_transmit``) is a question the shell asks before each frame.

Evidence comes from two channels: the peer's ``/role`` answers (or their failure), and
the bus (frames heard). The invariants:

* **Lease check.** ``may_transmit(now)`` is true only while ACTIVE, before the lease's
  expiry, and when the previous input is at most ``max_gap`` (half a lease) old. The
  shell asks it before every frame; a process resumed after SIGSTOP or a VM pause
  therefore gets a no on a stale lease before anything else happens.
* **Leases follow frames.** With the keep-alive on, the active's lease never reaches
  past its last frame (or its takeover) plus ``frame_reach`` (``takeover_after`` minus
  ``hearing_delay`` minus ``max_gap``). Any frame it sends is thus heard by the standby
  before the standby's quiet wait can end, so a standby that has heard the active's
  current reign can take over only after that reign's lease is gone, whatever the
  network does. Two leases can overlap only when two standbys take over before either
  heard the other's first frame (see the page); the priority stagger keeps
  their waits apart when each knows the other's priority.
* **Time jumps.** An input more than ``max_gap`` after the previous one means the
  process was frozen: an active steps down, and evidence received until then (and at
  that instant, possibly queued during the freeze) no longer counts.
* **Takeover.** A standby takes over only when the peer's lease as last reported has
  expired, the peer's latest fresh answer is standby or its latest poll failed, and the
  bus has carried no intact frame for ``takeover_after`` plus its stagger (a lease per
  rank below the peer's priority). A slave answers only when asked, so any intact frame
  proves a master; starting, restarting or resuming from a jump restarts the quiet wait.
* **No pre-emption.** A peer answering active, or frames on the bus, keep a standby
  standby whatever the priorities.

After a takeover the shell keeps the line's quiet time before its first frame; nothing
here models that beyond ``may_transmit``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Final

NEVER: Final = float("-inf")
#: From the lease check's yes to the peer noticing the bus busy: the bytes reach it a
#: character later (any byte counts as traffic, not only a whole frame), plus the
#: scheduling of two processes. ``takeover_after`` must exceed the lease plus this.
HEARING_DELAY_S: Final = 0.3
#: The bits of a priority (0..255), and of the random tie-break (``Contest``).
_PRIORITY_BITS: Final = 8
_TIEBREAK_BITS: Final = 32
_TIEBREAK_MASK: Final = (1 << _TIEBREAK_BITS) - 1
_KEY_BITS: Final = _PRIORITY_BITS + _TIEBREAK_BITS


class Role(StrEnum):
    """The role of one gateway, covering all its lines."""

    ACTIVE = "active"
    STANDBY = "standby"


class ChangeReason(StrEnum):
    """Why the role changed: one log line per change names it."""

    TAKEOVER = "takeover"  # peer's lease expired, peer not active, bus quiet long enough
    ANOTHER_MASTER = "another_master"  # heard a master frame this gateway did not send
    PEER_ACTIVE = "peer_active"  # the peer answered /role as active while this one was
    LEASE_EXPIRED = "lease_expired"  # not renewed in time (no evidence, or no frame sent)
    TIME_JUMP = "time_jump"  # the clock moved more than half a lease between inputs


class PeerState(StrEnum):
    """The peer as the latest fresh evidence shows it."""

    ACTIVE = "active"
    STANDBY = "standby"
    UNREACHABLE = "unreachable"  # the latest poll failed or timed out
    UNKNOWN = "unknown"  # no evidence newer than a lease, or only stale evidence


@dataclass(frozen=True, slots=True)
class RoleReport:
    """What ``GET /role`` answers: the peer reads it to decide."""

    role: Role
    #: While active: how long the peer must respect this gateway's lease from now on (a
    #: full lease: the claim the peer acknowledges, see ``peer_lease_remaining``).
    lease_remaining: float
    priority: int
    #: How long this gateway still respects its peer's lease from now on: the peer's
    #: acknowledged claim, which lets it keep its lease through a long silence.
    peer_lease_remaining: float = 0.0


@dataclass(frozen=True, slots=True)
class RoleChange:
    """One role change, for one log line and the takeover counter."""

    at: float
    role: Role  # the new role
    reason: ChangeReason


@dataclass(frozen=True, slots=True)
class KeepAlive:
    """The active sent nothing for half a lease: a frame now lets the standby hear it."""

    at: float


@dataclass(frozen=True, slots=True)
class RoleTiming:
    """The pair's times, and the ones derived from them (all in seconds)."""

    lease: float = 1.0
    takeover_after: float = 1.5
    #: From ``may_transmit``'s yes to the peer's handling of that frame: the longest
    #: frame at the line's speed, its end of frame and the peer's latency.
    hearing_delay: float = 0.3
    keepalive: bool = True

    def __post_init__(self) -> None:
        if self.lease <= 0 or self.hearing_delay < 0:
            raise ValueError("lease must be > 0 and hearing_delay >= 0")
        if self.takeover_after <= self.lease + self.hearing_delay:
            raise ValueError(
                f"takeover_after ({self.takeover_after} s) must exceed lease + hearing_delay"
                f" ({self.lease + self.hearing_delay} s): a frame sent at half a lease must"
                " be heard before the standby's wait ends"
            )

    @property
    def heartbeat(self) -> float:
        """The longest a live shell goes without an input (``get_timer`` sees to it)."""
        return self.lease / 4

    @property
    def max_gap(self) -> float:
        """A longer gap between inputs is a time jump: the process was frozen."""
        return self.lease / 2

    @property
    def keepalive_every(self) -> float:
        """The active sends a keep-alive after this long without a frame."""
        return self.lease / 2

    @property
    def frame_reach(self) -> float:
        """How long past its last frame (or its takeover) an active's lease may run."""
        return self.takeover_after - self.hearing_delay - self.max_gap


class PeerView:
    """What the peer's ``/role`` said, when, and whether the latest poll failed."""

    def __init__(self) -> None:
        self.role: Role | None = None
        self.priority: int | None = None
        self.answered_at = NEVER
        self.failed_at = NEVER
        #: Until when the peer respects this gateway's lease, as a local time: the poll's
        #: sending time plus what the peer said (it answered later: the safe side).
        self.acked_until = NEVER
        #: The latest lease expiry it ever reported, as a local time (receipt + remaining:
        #: later than the truth, the answer being late already, so on the safe side).
        self.lease_expiry = NEVER

    def answered(
        self,
        now: float,
        role: Role,
        lease_remaining: float,
        priority: int,
        acked_until: float = NEVER,
    ) -> None:
        """Note a fresh answer."""
        self.acked_until = acked_until
        self.role = role
        self.priority = priority
        self.answered_at = now
        if lease_remaining > 0:  # a standby claims nothing
            self.lease_expiry = max(self.lease_expiry, now + lease_remaining)

    def failed(self, now: float) -> None:
        """Note a poll that failed or timed out."""
        self.failed_at = now

    def state(self, now: float, stale_until: float, freshness: float) -> PeerState:
        """The peer as evidence received after ``stale_until`` and within ``freshness`` shows it."""
        latest = max(self.answered_at, self.failed_at)
        if latest <= stale_until or now > latest + freshness:
            return PeerState.UNKNOWN
        if self.failed_at > self.answered_at or self.role is None:
            return PeerState.UNREACHABLE
        return PeerState.ACTIVE if self.role is Role.ACTIVE else PeerState.STANDBY


class Contest:
    """The re-arbitration back-off: who waits longer after two masters met.

    With the peer's priority known and different, the lower waits a lease more (rank 1).
    Known and equal, contest ``n`` ranks by bit ``n - 1`` of ``tiebreak``, a number each
    gateway draws at random: two draws differ in some bit, so a round comes where exactly
    one waits longer (about two rounds on average). Unknown (the network down), by the bits
    of the priority first (distinct priorities differ in one of their 8 bits), then by
    those of ``tiebreak``.
    """

    def __init__(self, priority: int, tiebreak: int = 0) -> None:
        self.priority = priority
        self.tiebreak = tiebreak & _TIEBREAK_MASK
        self.count = 0

    def rank(self, peer_priority: int | None) -> int:
        """0 for the one that goes first, 1 for the one that waits a lease more."""
        if peer_priority is not None and peer_priority != self.priority:
            return 1 if peer_priority > self.priority else 0
        if self.count == 0:
            return 0
        if peer_priority is None:
            key, bits = self.priority | self.tiebreak << _PRIORITY_BITS, _KEY_BITS
        else:
            key, bits = self.tiebreak, _TIEBREAK_BITS
        return 1 - ((key >> ((self.count - 1) % bits)) & 1)


class RoleMachine:
    """One gateway's role: inputs with ``now``, the lease check, the next deadline.

    Every comparison with time is written ``now >= instant + span``, the same sum
    ``get_timer`` returns, so a timer run at the deadline sees it reached despite rounding.
    """

    def __init__(
        self,
        priority: int,
        *,
        start: float,
        lease: float = 1.0,
        takeover_after: float = 1.5,
        hearing_delay: float = 0.3,
        keepalive: bool = True,
        tiebreak: int = 0,
    ) -> None:
        self.timing = RoleTiming(lease, takeover_after, hearing_delay, keepalive)
        self.priority = priority
        self._role = Role.STANDBY
        self.peer = PeerView()
        self.contest = Contest(priority, tiebreak)
        #: Actions for the shell, oldest first: role changes, and keep-alives to send.
        self.changes: list[RoleChange] = []
        self.keepalives: list[KeepAlive] = []
        self._last_input = start
        self._stale_until = NEVER  # peer evidence received at or before it is stale
        self._watching_since = start  # the bus has been watched without a gap since
        self._heard_at = NEVER  # the last intact frame heard
        self._sent_at = NEVER  # the last frame this gateway sent
        self._active_since = NEVER
        self._expiry = NEVER
        self._yielding = False  # stepped down, the peer not heard since: the peer goes first

    @property
    def role(self) -> Role:
        """ACTIVE or STANDBY (a gateway starts STANDBY)."""
        return self._role

    # -- inputs ------------------------------------------------------------------------

    def peer_report(
        self,
        now: float,
        role: Role,
        lease_remaining: float,
        priority: int,
        peer_lease_remaining: float = 0.0,
        asked_at: float | None = None,
    ) -> None:
        """A fresh answer of the peer's ``/role``, asked at ``asked_at`` (default ``now``)."""
        self._advance(now)
        asked = now if asked_at is None else min(asked_at, now)
        acked = asked + peer_lease_remaining if peer_lease_remaining > 0 else NEVER
        self.peer.answered(now, role, lease_remaining, priority, acked)
        self._yielding = False
        if role is Role.ACTIVE and self.role is Role.ACTIVE:
            self.contest.count += 1
            self._step_down(now, ChangeReason.PEER_ACTIVE)
        self._decide(now)

    def peer_unreachable(self, now: float) -> None:
        """A poll of the peer's ``/role`` failed or timed out."""
        self._advance(now)
        self.peer.failed(now)
        self._decide(now)

    def master_frame_heard(self, now: float) -> None:
        """A master frame this gateway did not send (own echo filtered before)."""
        self._advance(now)
        self._heard_at = now
        if self.role is Role.ACTIVE:
            self.contest.count += 1
            self._step_down(now, ChangeReason.ANOTHER_MASTER)
        self._decide(now)

    def frame_heard(self, now: float) -> None:
        """Any intact frame: the bus is alive (a slave answers only when asked)."""
        self._advance(now)
        self._heard_at = now
        self._decide(now)

    def transmitted(self, now: float) -> None:
        """This gateway sent a frame (call at the instant ``may_transmit`` said yes)."""
        self._advance(now)
        self._sent_at = now
        self._decide(now)

    def handle_timer(self, now: float) -> None:
        """Time passed: run at ``get_timer()`` (earlier is harmless). An active that has
        sent nothing for half a lease asks for a keep-alive (``keepalives``)."""
        self._advance(now)
        self._decide(now)
        if self.keepalive_due(now):
            self.keepalives.append(KeepAlive(now))

    def drain_changes(self) -> list[RoleChange]:
        """The role changes since the last drain, oldest first."""
        changes, self.changes = self.changes, []
        return changes

    # -- outputs -----------------------------------------------------------------------

    def may_transmit(self, now: float) -> bool:
        """The lease check the shell makes before every frame it sends."""
        return (
            self.role is Role.ACTIVE
            and now < self._expiry
            and now <= self._last_input + self.timing.max_gap
        )

    def lease_remaining(self, now: float) -> float:
        """Seconds the lease still runs (0 unless it may transmit now)."""
        return self._expiry - now if self.may_transmit(now) else 0.0

    def report(self, now: float) -> RoleReport:
        """The answer of ``GET /role``: active only while the lease holds.

        Answered between a freeze and the next input, a void lease says standby: this
        gateway will step down at that input, and must not make a new active step down.
        """
        respected = max(0.0, self.peer.lease_expiry - now)
        if self.may_transmit(now):
            return RoleReport(Role.ACTIVE, self.timing.lease, self.priority, respected)
        return RoleReport(Role.STANDBY, 0.0, self.priority, respected)

    def keepalive_due(self, now: float) -> bool:
        """True when the active has sent nothing for half a lease (keep-alive on): what
        ``handle_timer`` asks before it emits a ``KeepAlive``."""
        return (
            self.timing.keepalive
            and self.role is Role.ACTIVE
            and now >= self._sent_at + self.timing.keepalive_every
        )

    def get_timer(self) -> float:
        """When ``handle_timer`` must next run: never more than a quarter lease away."""
        deadline = self._last_input + self.timing.heartbeat
        if self.role is Role.ACTIVE:
            candidates = [self._expiry]
            if self.timing.keepalive:
                candidates.append(self._sent_at + self.timing.keepalive_every)
        else:
            claimed = self.peer.lease_expiry + self.timing.hearing_delay
            candidates = [max(self._takeover_at(), claimed)]
        for at in candidates:
            if self._last_input < at < deadline:
                deadline = at
        return deadline

    def takeover_at(self) -> float:
        """The earliest instant the bus alone would let this standby take over."""
        return self._takeover_at()

    # -- decisions ---------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Detect a time jump and a lapsed lease before any evidence is taken."""
        if now < self._last_input:
            raise ValueError(f"time went backwards: {now} < {self._last_input}")
        if now > self._last_input + self.timing.max_gap:
            self._stale_until = now
            self._watching_since = now
            if self.role is Role.ACTIVE:
                self._step_down(now, ChangeReason.TIME_JUMP)
        self._last_input = now
        if self.role is Role.ACTIVE and now >= self._expiry:
            self._step_down(now, ChangeReason.LEASE_EXPIRED)

    def _decide(self, now: float) -> None:
        if self.role is Role.ACTIVE:
            self._renew(now)
        elif self._may_take_over(now):
            self._take_over(now)

    def _peer_state(self, now: float) -> PeerState:
        return self.peer.state(now, self._stale_until, self.timing.lease)

    def _renew(self, now: float) -> None:
        """Extend the lease while the evidence allows (a foreign frame stepped us down)."""
        if self._peer_state(now) in (PeerState.STANDBY, PeerState.UNREACHABLE):
            self._expiry = self._lease_until(now)
            if now >= self._active_since + self.timing.takeover_after:
                self.contest.count = 0

    def _lease_until(self, now: float) -> float:
        """A lease, cut to what the bus or the peer vouches for: the frames' reach past the
        last frame (heard by the standby before its quiet wait ends), or the time the peer
        acknowledged it respects (it takes over only a hearing delay after that)."""
        until = now + self.timing.lease
        if self.timing.keepalive:
            reference = max(self._sent_at, self._active_since)
            by_frames = min(until, reference + self.timing.frame_reach)
            return max(by_frames, min(until, self.peer.acked_until))
        return until

    def _takeover_at(self) -> float:
        quiet_since = max(self._watching_since, self._heard_at, self._sent_at)
        return quiet_since + self.timing.takeover_after + self.timing.lease * self._rank()

    def _rank(self) -> int:
        """The stagger: none after the active peer went silent (a kill: no contest), one
        lease for a gateway that stepped down until the peer answers again, else by
        priority (``Contest``)."""
        if self._yielding:
            return 1
        peer = self.peer
        if peer.role is Role.ACTIVE and self._active_since < peer.answered_at:
            return 0
        return self.contest.rank(peer.priority)

    def _may_take_over(self, now: float) -> bool:
        # A frame the peer sends before the lease it claimed ends reaches this gateway a
        # hearing delay later at most: only then has silence proved anything.
        if now < self.peer.lease_expiry + self.timing.hearing_delay:
            return False
        if self._peer_state(now) not in (PeerState.STANDBY, PeerState.UNREACHABLE):
            return False
        return now >= self._takeover_at()

    def _take_over(self, now: float) -> None:
        self._role = Role.ACTIVE
        self._active_since = now
        self._expiry = self._lease_until(now)
        self.changes.append(RoleChange(now, Role.ACTIVE, ChangeReason.TAKEOVER))

    def _step_down(self, now: float, reason: ChangeReason) -> None:
        # A lease lost to silence or a freeze: the peer may be taking over; let it go first
        # (two masters that met re-arbitrate by ``Contest`` instead).
        self._yielding = reason in (ChangeReason.LEASE_EXPIRED, ChangeReason.TIME_JUMP)
        self._role = Role.STANDBY
        self._expiry = NEVER
        self.changes.append(RoleChange(now, Role.STANDBY, reason))
