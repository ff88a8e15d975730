"""The redundancy role machine, with literal times (defaults: lease 1 s, takeover_after 1.5 s).

Derived times used below: the shell's timer runs at least every 0.25 s (a quarter lease); a
gap of more than 0.5 s between inputs is a time jump; the keep-alive is due after 0.5 s
without a frame; the active's lease reaches at most 0.7 s past its last frame or its
takeover (1.5 - hearing_delay 0.3 - 0.5).

At the end, a hypothesis stateful test of two machines on a simulated network and bus
(``PairOnOneBus``): the exclusion guarantee and the liveness bound of docs/redundancy.md.
"""

from __future__ import annotations

import enum
import heapq
import os
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    rule,
)

from gateway.core.redundancy import (
    ChangeReason,
    Contest,
    KeepAlive,
    Role,
    RoleChange,
    RoleMachine,
    RoleReport,
    RoleTiming,
)


def _times(start: float, stop: float, step: float = 0.25) -> list[float]:
    """Instants ``start``, ``start + step``, ... up to ``stop`` included (exact binary steps)."""
    count = round((stop - start) / step)
    return [start + i * step for i in range(count + 1)]


def _run(
    machine: RoleMachine,
    start: float,
    stop: float,
    each: Callable[[RoleMachine, float], None],
    step: float = 0.25,
) -> None:
    """Call ``each`` then ``handle_timer`` at every instant; transmit the keep-alives it
    asks for."""
    for now in _times(start, stop, step):
        each(machine, now)
        machine.handle_timer(now)
        if _keepalive_asked(machine) and machine.may_transmit(now):
            machine.transmitted(now)


def _keepalive_asked(machine: RoleMachine) -> bool:
    """Whether ``handle_timer`` asked for a keep-alive since the last look (the action
    taken, as the shell takes it)."""
    asked = bool(machine.keepalives)
    machine.keepalives.clear()
    return asked


def _role(machine: RoleMachine) -> Role:
    """The role, read through a call so that the type checker does not pin it between steps."""
    return machine.role


def _unreachable(machine: RoleMachine, now: float) -> None:
    machine.peer_unreachable(now)


def _unreachable_and_busy(machine: RoleMachine, now: float) -> None:
    machine.peer_unreachable(now)
    machine.master_frame_heard(now)


def _active_lone(priority: int = 1) -> RoleMachine:
    """A lone gateway that took over at 1.5 (peer unreachable, bus quiet since 0)."""
    machine = RoleMachine(priority, start=0.0)
    _run(machine, 0.25, 1.5, _unreachable)
    assert _role(machine) is Role.ACTIVE
    return machine


def _pair_step(active: RoleMachine, standby: RoleMachine, now: float, network: bool,
               holding: bool) -> None:  # fmt: skip
    """One step of a pair: each polls the other (instantly, or the poll fails), and whoever
    is active sends a keep-alive when due (``active``'s line is held while ``holding``);
    the other hears it at once."""
    for asking, asked in ((active, standby), (standby, active)):
        if network:
            report = asked.report(now)
            asking.peer_report(now, report.role, report.lease_remaining, report.priority,
                               report.peer_lease_remaining, asked_at=now)  # fmt: skip
        else:
            asking.peer_unreachable(now)
    for machine in (active, standby):
        machine.handle_timer(now)
    for sender, hearer in ((active, standby), (standby, active)):
        wanted = _keepalive_asked(sender)
        if holding and sender is active:
            continue  # its line waits for a slave's answer (asked again at the next timer)
        if wanted and sender.may_transmit(now):
            sender.transmitted(now)
            hearer.master_frame_heard(now)


def _pair(until: float) -> tuple[RoleMachine, RoleMachine]:
    """A (priority 2) active and B standby, on a fine network, from 0 to ``until``."""
    a, b = RoleMachine(2, start=0.0), RoleMachine(1, start=0.0)
    for now in _times(0.25, until, 0.25):
        first, second = (a, b) if a.role is Role.ACTIVE or b.role is not Role.ACTIVE else (b, a)
        _pair_step(first, second, now, network=True, holding=False)
    assert (a.role, b.role) == (Role.ACTIVE, Role.STANDBY)
    return a, b


def test_an_active_whose_standby_acknowledges_its_lease_keeps_it_through_a_long_silence() -> None:
    """A slave that takes 2 s (or a first contact waited 1 s): the bus is silent, but the
    standby, which answers /role, respects the active's claim, so no failover."""
    a, b = _pair(4.0)
    for now in _times(4.25, 7.0, 0.25):
        _pair_step(a, b, now, network=True, holding=True)
        assert a.may_transmit(now) and not b.may_transmit(now)
    assert a.changes == [] or all(c.role is Role.ACTIVE for c in a.changes)


def test_a_network_cut_during_a_long_silence_never_makes_two_writers() -> None:
    """The cut comes while the active's line is held: its lease ends by what the standby
    acknowledged, and the standby takes over only a hearing delay after that."""
    a, b = _pair(4.0)
    for now in _times(4.25, 5.0, 0.25):
        _pair_step(a, b, now, network=True, holding=True)
    last_ack = a.peer.acked_until
    took_over = None
    for now in _times(5.05, 9.0, 0.05):
        _pair_step(a, b, now, network=False, holding=True)
        assert not (a.may_transmit(now) and b.may_transmit(now)), now
        if a.may_transmit(now):
            assert now < last_ack
        if took_over is None and b.role is Role.ACTIVE:
            took_over = now
    assert took_over is not None and took_over >= last_ack + 0.3


def test_a_lone_gateway_takes_over_after_takeover_after_of_quiet_bus() -> None:
    machine = RoleMachine(1, start=0.0)
    assert _role(machine) is Role.STANDBY
    _run(machine, 0.25, 1.25, _unreachable)
    assert _role(machine) is Role.STANDBY
    assert machine.get_timer() == 1.5
    machine.peer_unreachable(1.5)
    assert _role(machine) is Role.ACTIVE
    assert machine.drain_changes() == [RoleChange(1.5, Role.ACTIVE, ChangeReason.TAKEOVER)]
    assert machine.may_transmit(1.5)
    assert machine.keepalive_due(1.5)  # it announces itself at once
    report = machine.report(1.5)
    assert (report.role, report.priority) == (Role.ACTIVE, 1)
    assert report.lease_remaining == 1.0  # the claim the peer is to respect: a full lease
    assert machine.lease_remaining(1.5) == pytest.approx(0.7)  # its own: 0.7 past the takeover


def test_no_takeover_without_any_word_from_the_peer() -> None:
    """Neither an answer nor a failed poll: no evidence, no takeover."""
    machine = RoleMachine(1, start=0.0)
    _run(machine, 0.25, 10.0, lambda m, now: None)
    assert _role(machine) is Role.STANDBY


def test_a_standby_whose_peer_answers_active_never_takes_over() -> None:
    machine = RoleMachine(9, start=0.0)
    _run(machine, 0.25, 20.0, lambda m, now: m.peer_report(now, Role.ACTIVE, 1.0, 1))
    assert _role(machine) is Role.STANDBY
    assert machine.changes == []
    assert not machine.may_transmit(20.0)
    # It respects the active's claimed lease (the acknowledgement the active renews by).
    assert machine.report(20.0) == RoleReport(Role.STANDBY, 0.0, 9, 1.0)


def test_peer_unreachable_but_master_frames_every_half_second_keeps_it_standby() -> None:
    def each(machine: RoleMachine, now: float) -> None:
        machine.peer_unreachable(now)
        if now % 0.5 == 0:
            machine.master_frame_heard(now)

    machine = RoleMachine(1, start=0.0)
    _run(machine, 0.25, 20.0, each)
    assert _role(machine) is Role.STANDBY
    assert machine.changes == []


def test_slave_answers_alone_keep_the_standby_standby() -> None:
    """An intact slave answer proves a master asked, even when the request was not heard."""

    def each(machine: RoleMachine, now: float) -> None:
        machine.peer_unreachable(now)
        if now % 1.25 == 0:
            machine.frame_heard(now)

    machine = RoleMachine(1, start=0.0)
    _run(machine, 0.25, 20.0, each)
    assert _role(machine) is Role.STANDBY


def test_the_bus_going_quiet_lets_the_standby_take_over_takeover_after_later() -> None:
    machine = RoleMachine(1, start=0.0)
    _run(machine, 0.25, 3.0, _unreachable_and_busy)
    _run(machine, 3.25, 4.25, _unreachable)
    assert _role(machine) is Role.STANDBY
    machine.peer_unreachable(4.5)
    assert _role(machine) is Role.ACTIVE  # 3.0 + 1.5


def test_takeover_waits_for_the_lease_the_peer_last_reported() -> None:
    machine = RoleMachine(1, start=0.0)
    machine.peer_report(0.25, Role.ACTIVE, 2.5, 2)  # the peer's lease runs to 2.75 here
    _run(machine, 0.5, 2.5, _unreachable)
    assert _role(machine) is Role.STANDBY  # the bus has been quiet long enough since 1.5
    # A frame sent just before 2.75 is heard a hearing delay (0.3 s) later at most.
    for now in (2.75, 3.0):
        machine.handle_timer(now)
        assert _role(machine) is Role.STANDBY
    assert machine.get_timer() == pytest.approx(3.05)
    machine.handle_timer(3.05)
    assert _role(machine) is Role.ACTIVE


def test_a_standby_answer_lets_the_higher_priority_take_over_and_the_lower_wait() -> None:
    high = RoleMachine(2, start=0.0)
    _run(high, 0.25, 1.5, lambda m, now: m.peer_report(now, Role.STANDBY, 0.0, 1))
    assert _role(high) is Role.ACTIVE
    assert high.changes[0].at == 1.5
    low = RoleMachine(1, start=0.0)
    _run(low, 0.25, 2.25, lambda m, now: m.peer_report(now, Role.STANDBY, 0.0, 2))
    assert _role(low) is Role.STANDBY
    assert low.get_timer() == 2.5  # 1.5 + one lease of stagger
    low.handle_timer(2.5)
    assert _role(low) is Role.ACTIVE


def test_an_active_hearing_a_foreign_master_steps_down_at_once() -> None:
    machine = _active_lone()
    _run(machine, 1.75, 3.0, _unreachable)
    assert machine.may_transmit(3.0)
    machine.master_frame_heard(3.125)
    assert _role(machine) is Role.STANDBY
    assert not machine.may_transmit(3.125)
    assert machine.lease_remaining(3.125) == 0.0
    assert not machine.keepalive_due(3.125)
    assert machine.drain_changes()[-1] == RoleChange(
        3.125, Role.STANDBY, ChangeReason.ANOTHER_MASTER
    )


@pytest.mark.parametrize(("peer_priority", "back_at"), [(5, 6.5), (0, 5.5)])
def test_it_stays_silent_while_foreign_frames_go_on_then_re_arbitrates_by_priority(
    peer_priority: int, back_at: float
) -> None:
    """The lower priority waits a lease more after the frames stop at 4.0."""
    machine = RoleMachine(1, start=0.0)
    machine.peer_report(0.25, Role.STANDBY, 0.0, peer_priority)
    _run(machine, 0.5, 2.5, _unreachable)
    assert _role(machine) is Role.ACTIVE
    _run(machine, 2.75, 4.0, _unreachable_and_busy)
    assert _role(machine) is Role.STANDBY
    assert [c.reason for c in machine.changes][-1] is ChangeReason.ANOTHER_MASTER
    _run(machine, 4.25, back_at - 0.25, _unreachable)
    assert _role(machine) is Role.STANDBY
    machine.peer_unreachable(back_at)
    assert _role(machine) is Role.ACTIVE


def test_with_no_priority_known_contests_rank_by_the_bits_of_the_priority() -> None:
    one, two = Contest(1), Contest(2)
    assert (one.rank(None), two.rank(None)) == (0, 0)  # nothing known: nobody waits
    one.count = two.count = 1
    assert (one.rank(None), two.rank(None)) == (0, 1)  # bit 0 differs
    one.count = two.count = 2
    assert (one.rank(None), two.rank(None)) == (1, 0)  # bit 1 differs
    assert (one.rank(2), two.rank(1)) == (1, 0)  # a known priority decides


def test_equal_priorities_separate_by_their_random_tiebreaks() -> None:
    one, two = Contest(5, tiebreak=0b0110), Contest(5, tiebreak=0b0101)
    assert (one.rank(5), two.rank(5)) == (0, 0)  # the first meeting: nobody knows to wait
    one.count = two.count = 1
    assert (one.rank(5), two.rank(5)) == (1, 0)  # bit 0 of the draws differs
    one.count = two.count = 2
    assert (one.rank(5), two.rank(5)) == (0, 1)  # bit 1
    # The peer's priority unknown: the priority's 8 bits first, then the draw's.
    one.count = two.count = 9
    assert (one.rank(None), two.rank(None)) == (1, 0)


def _equal_pair(tiebreaks: tuple[int, int], until: float) -> tuple[RoleMachine, RoleMachine]:
    """Two gateways of priority 7 started together on a fine network; each frame reaches
    the other 0.1 s after it is sent (a 30-character frame at 9600 baud)."""
    a = RoleMachine(7, start=0.0, tiebreak=tiebreaks[0])
    b = RoleMachine(7, start=0.0, tiebreak=tiebreaks[1])
    in_flight: list[tuple[float, RoleMachine]] = []  # (heard at, by whom)
    for now in _times(0.05, until, 0.05):
        for at, hearer in [item for item in in_flight if item[0] <= now]:
            in_flight.remove((at, hearer))
            hearer.master_frame_heard(now)
        # The two run at once: each answers as it stood before hearing the other.
        reports = ((a, b.report(now)), (b, a.report(now)))
        for asking, report in reports:
            asking.peer_report(now, report.role, report.lease_remaining, report.priority,
                               report.peer_lease_remaining, asked_at=now)  # fmt: skip
        for machine in (a, b):
            machine.handle_timer(now)
        for sender, hearer in ((a, b), (b, a)):
            if _keepalive_asked(sender) and sender.may_transmit(now):
                sender.transmitted(now)
                in_flight.append((now + 0.1, hearer))
    return a, b


def test_two_gateways_of_equal_priority_started_together_end_with_one_active() -> None:
    """Both take over at the same instant and hear each other's keep-alive: both step
    down. Equal priorities used to rank them equal in every contest after that, so they
    took over together again and again; their random draws now decide the second round."""
    a, b = _equal_pair((0x1234, 0x4321), 12.0)
    assert sorted([a.role, b.role]) == [Role.ACTIVE, Role.STANDBY]
    takeovers = [c.at for c in a.changes + b.changes if c.role is Role.ACTIVE]
    assert len(takeovers) == 3 and max(takeovers) < 6.0, takeovers  # 2 together, 1 alone


def test_a_frozen_active_may_not_transmit_on_the_first_call_after_the_jump() -> None:
    machine = _active_lone()
    _run(machine, 1.75, 3.0, _unreachable)
    assert machine.may_transmit(3.0)
    assert not machine.may_transmit(8.0)  # 5 s later, before any input
    assert machine.lease_remaining(8.0) == 0.0
    assert machine.report(8.0) == RoleReport(Role.STANDBY, 0.0, 1)  # /role asked first
    machine.peer_report(8.0, Role.ACTIVE, 1.0, 2)
    assert _role(machine) is Role.STANDBY
    assert machine.drain_changes()[-1] == RoleChange(8.0, Role.STANDBY, ChangeReason.TIME_JUMP)


def test_after_a_jump_only_fresh_evidence_and_a_fresh_quiet_wait_count() -> None:
    machine = _active_lone()
    _run(machine, 1.75, 3.0, _unreachable)
    machine.peer_unreachable(8.0)  # possibly queued during the freeze: stale
    assert _role(machine) is Role.STANDBY
    _run(machine, 8.25, 10.25, _unreachable)
    # The quiet wait restarted at 8.0, and a gateway whose lease lapsed in a freeze lets
    # the peer go first: a lease more (8.0 + 1.5 + 1.0).
    assert _role(machine) is Role.STANDBY
    machine.peer_unreachable(10.5)
    assert _role(machine) is Role.ACTIVE


def test_a_jump_of_more_than_half_a_lease_makes_a_standby_watch_again() -> None:
    machine = RoleMachine(1, start=0.0)
    _run(machine, 0.25, 1.0, _unreachable)
    machine.peer_unreachable(1.75)  # a 0.75 s gap: frames may have been missed
    machine.handle_timer(1.75)
    assert _role(machine) is Role.STANDBY
    assert machine.takeover_at() == 3.25


def test_a_pause_of_half_a_lease_is_not_a_jump() -> None:
    machine = _active_lone()
    machine.peer_unreachable(1.75)
    assert machine.may_transmit(2.0)  # 0.25 s after the last input, lease to 2.2
    assert not machine.may_transmit(2.3)  # past the lease
    machine.handle_timer(2.0)
    assert _role(machine) is Role.ACTIVE


def test_an_active_that_sends_nothing_loses_its_lease_at_its_reach() -> None:
    machine = _active_lone()
    machine.peer_unreachable(1.75)
    machine.handle_timer(2.0)
    assert machine.get_timer() == pytest.approx(2.2)  # 1.5 + 0.7, nothing sent
    machine.handle_timer(2.2)
    assert _role(machine) is Role.STANDBY
    assert machine.changes[-1].reason is ChangeReason.LEASE_EXPIRED


def test_keep_alives_keep_the_lease_for_as_long_as_the_evidence_holds() -> None:
    machine = _active_lone()
    _run(machine, 1.75, 30.0, _unreachable)
    assert _role(machine) is Role.ACTIVE
    assert machine.changes == [RoleChange(1.5, Role.ACTIVE, ChangeReason.TAKEOVER)]
    assert 0.5 <= machine.lease_remaining(30.0) <= 1.0
    assert not machine.keepalive_due(30.0)
    assert machine.keepalive_due(30.5)


def test_the_timer_asks_for_a_keep_alive_half_a_lease_after_the_last_frame() -> None:
    """The keep-alive is an action out of ``handle_timer``, as the line core's are."""
    machine = _active_lone()  # its first keep-alive went out at the takeover, 1.5
    machine.peer_unreachable(1.75)
    machine.handle_timer(1.75)
    assert machine.keepalives == []
    machine.handle_timer(2.0)
    assert machine.keepalives == [KeepAlive(2.0)]


def test_without_evidence_from_the_peer_the_lease_runs_out() -> None:
    machine = _active_lone()
    _run(machine, 1.75, 3.0, _unreachable)
    _run(machine, 3.25, 5.0, lambda m, now: None)  # polls hang: neither answer nor failure
    assert _role(machine) is Role.STANDBY
    assert machine.changes[-1].reason is ChangeReason.LEASE_EXPIRED
    assert 4.0 <= machine.changes[-1].at <= 4.75


def test_the_peer_answering_active_makes_the_active_step_down() -> None:
    machine = _active_lone()
    machine.peer_report(1.75, Role.ACTIVE, 0.5, 2)
    assert _role(machine) is Role.STANDBY
    assert machine.changes[-1] == RoleChange(1.75, Role.STANDBY, ChangeReason.PEER_ACTIVE)


def test_the_old_active_restarted_while_the_peer_is_active_stays_standby() -> None:
    def each(machine: RoleMachine, now: float) -> None:
        machine.peer_report(now, Role.ACTIVE, 1.0, 1)
        if now % 0.5 == 0:
            machine.master_frame_heard(now)

    restarted = RoleMachine(100, start=50.0)  # the higher priority: no pre-emption anyway
    _run(restarted, 50.25, 70.0, each)
    assert _role(restarted) is Role.STANDBY
    assert restarted.changes == []


class _Pair:
    """Two machines on a perfect network (reports every 0.25 s) and a bus (0.0625 s late)."""

    STEP = 0.0625

    def __init__(self, a: RoleMachine, b: RoleMachine, b_from: float = 0.0) -> None:
        self.nodes = (a, b)
        self.b_from = b_from
        self.frames: list[tuple[float, int]] = []  # (heard at, by node)

    def run(self, stop: float) -> None:
        for now in _times(0.0, stop, self.STEP):
            for index, machine in enumerate(self.nodes):
                if index == 1 and now < self.b_from:
                    continue
                self._step(index, machine, now)

    def _step(self, index: int, machine: RoleMachine, now: float) -> None:
        peer = self.nodes[1 - index]
        for at, by in list(self.frames):
            if by == index and at <= now:
                self.frames.remove((at, by))
                machine.master_frame_heard(now)
        if now % 0.25 == 0 and now > 0:
            if index == 0 and now < self.b_from:
                machine.peer_unreachable(now)
            else:
                report = peer.report(now)
                machine.peer_report(now, report.role, report.lease_remaining, report.priority)
        machine.handle_timer(now)
        if _keepalive_asked(machine) and machine.may_transmit(now):
            machine.transmitted(now)
            self.frames.append((now + self.STEP, 1 - index))


@pytest.mark.parametrize("b_from", [0.0, 0.5, 0.9375])
def test_started_within_a_lease_the_higher_priority_is_active_first_the_lower_never(
    b_from: float,
) -> None:
    high, low = RoleMachine(2, start=b_from), RoleMachine(1, start=0.0)
    pair = _Pair(low, high, b_from=b_from)
    pair.run(20.0)
    assert _role(high) is Role.ACTIVE
    assert [c.reason for c in high.changes] == [ChangeReason.TAKEOVER]
    assert high.changes[0].at == b_from + 1.5
    assert low.changes == []


def test_started_more_than_a_lease_later_the_higher_priority_does_not_pre_empt() -> None:
    high, low = RoleMachine(2, start=2.0), RoleMachine(1, start=0.0)
    pair = _Pair(low, high, b_from=2.0)
    pair.run(20.0)
    assert _role(low) is Role.ACTIVE
    assert high.changes == []


def test_without_keepalive_the_lease_is_not_bound_to_frames() -> None:
    machine = RoleMachine(1, start=0.0, keepalive=False)
    _run(machine, 0.25, 10.0, _unreachable)
    assert _role(machine) is Role.ACTIVE
    assert not machine.keepalive_due(10.0)
    assert machine.lease_remaining(10.0) == pytest.approx(1.0)


def test_timing_is_checked() -> None:
    with pytest.raises(ValueError, match="takeover_after"):
        RoleTiming(lease=1.0, takeover_after=1.2)
    with pytest.raises(ValueError, match="lease"):
        RoleTiming(lease=0.0)
    assert RoleTiming().frame_reach == pytest.approx(0.7)
    machine = RoleMachine(1, start=5.0)
    with pytest.raises(ValueError, match="backwards"):
        machine.handle_timer(4.0)


# -- two machines on a simulated network and bus, driven by hypothesis ------------------

POLL_EVERY = 0.25  # the shell polls the peer's /role this often
POLL_TIMEOUT = 0.2  # and gives a poll up after this long
BUS_DELAY = 0.25  # a frame is handled by the other gateway at most this late (< hearing_delay)
LIVENESS_BOUND = 1.0 + 1.5 + 1.0  # lease + takeover_after + one stagger


class _Kind(enum.Enum):
    TICK = "tick"  # the node's deadline
    POLL = "poll"  # the node polls its peer
    ARRIVE = "arrive"  # a poll reaches the peer's HTTP endpoint
    ANSWER = "answer"  # the peer's answer reaches the poller
    TIMEOUT = "timeout"  # the poller gives up on a poll
    FRAME = "frame"  # the other gateway's master frame reaches the node's port
    SLAVE = "slave"  # a slave's answer to it reaches the node's port


@dataclass(order=True)
class _Event:
    at: float
    seq: int
    kind: _Kind = field(compare=False)
    node: int = field(compare=False)
    incarnation: int = field(compare=False)  # -1: whichever process is there
    payload: Any = field(compare=False, default=None)


@dataclass
class _Node:
    """One gateway's process as the shell runs it, and what the checks need to know."""

    index: int
    priority: int
    machine: RoleMachine | None = None
    incarnation: int = 0
    frozen: bool = False
    backlog: list[_Event] = field(default_factory=list)
    tick_gen: int = 0
    poll_id: int | None = None
    poll_sent_at: float = 0.0  # when its pending poll went out (the acknowledgement's base)
    reign: int | None = None  # the id of its current reign as active
    seen: set[int] = field(default_factory=set)  # reigns of the other it heard frames of
    seen_at_takeover: frozenset[int] = frozenset()
    took_over_at: float | None = None
    busy_until: float = 0.0  # the line is held (a slave's answer awaited): no keep-alive


class PairOnOneBus(RuleBasedStateMachine):
    """Two role machines, a lossy partitionable network, a shared bus, freezes and kills.

    The shell is modelled: its timer runs at ``get_timer``, polls every 0.25 s (given up after
    0.2 s), a keep-alive whenever due and allowed, masters' requests at random; a frame
    sent reaches the other gateway within 0.25 s; frames reaching a frozen gateway wait
    in its kernel buffer and are read after it resumes (in either order with its timer);
    a resumed gateway that was about to send first asks ``may_transmit``.

    Checked on every event: two gateways that are both alive, unfrozen and allowed to
    transmit must have taken over each without having heard a frame of the other's
    current reign (the exact guarantee of docs/redundancy.md: a reign that has been heard
    is never overlapped; only simultaneous takeovers can be, until either hears the other).
    """

    def __init__(self) -> None:
        super().__init__()
        self.now = 0.0
        self.queue: list[_Event] = []
        self.seq = 0
        self.ids = 0
        self.rng = random.Random(0)
        self.links = {(0, 1): True, (1, 0): True}
        self.loss = 0.0
        self.net_delay = 0.05
        self.nodes: tuple[_Node, _Node] = (_Node(0, 2), _Node(1, 1))

    @initialize(
        seed=st.integers(0, 2**32 - 1), priorities=st.sampled_from([(2, 1), (1, 2), (5, 6)])
    )
    def start(self, seed: int, priorities: tuple[int, int]) -> None:
        self.rng = random.Random(seed)
        self.nodes = (_Node(0, priorities[0]), _Node(1, priorities[1]))
        for node in self.nodes:
            self._boot(node)

    # -- the simulated world ------------------------------------------------------------

    def _push(
        self, at: float, kind: _Kind, node: int, incarnation: int, payload: Any = None
    ) -> None:
        self.seq += 1
        heapq.heappush(self.queue, _Event(at, self.seq, kind, node, incarnation, payload))

    def _boot(self, node: _Node) -> None:
        node.machine = RoleMachine(node.priority, start=self.now)
        node.incarnation += 1
        node.frozen, node.backlog, node.poll_id = False, [], None
        node.reign, node.seen, node.took_over_at = None, set(), None
        self._push(
            self.now + self.rng.uniform(0, POLL_EVERY), _Kind.POLL, node.index, node.incarnation
        )
        self._arm(node)

    def _arm(self, node: _Node) -> None:
        assert node.machine is not None
        node.tick_gen += 1
        self._push(
            node.machine.get_timer(), _Kind.TICK, node.index, node.incarnation, node.tick_gen
        )

    def _net(self, src: int, dst: int) -> float | None:
        """The delay of one HTTP message, or None when it is lost."""
        if not self.links[(src, dst)] or self.rng.random() < self.loss:
            return None
        return self.rng.uniform(0.0, self.net_delay)

    def _run_until(self, until: float) -> None:
        while self.queue and self.queue[0].at <= until:
            event = heapq.heappop(self.queue)
            self.now = max(self.now, event.at)
            self._dispatch(event)
            self._check_exclusion()
        self.now = until

    def _dispatch(self, event: _Event) -> None:
        node = self.nodes[event.node]
        if node.machine is None or event.incarnation not in (-1, node.incarnation):
            return  # dead, or meant for a process that was killed since
        if event.kind is _Kind.TICK and event.payload != node.tick_gen:
            return  # a timer re-armed since
        if node.frozen:
            node.backlog.append(event)
            return
        self._deliver(node, event)
        self._after_input(node)

    def _deliver(self, node: _Node, event: _Event) -> None:
        machine, peer = node.machine, self.nodes[1 - node.index]
        assert machine is not None
        if event.kind is _Kind.TICK:
            machine.handle_timer(self.now)
        elif event.kind is _Kind.POLL:
            self._poll(node, peer)
        elif event.kind is _Kind.ARRIVE:
            report = machine.report(self.now)
            delay = self._net(node.index, peer.index)
            if delay is not None:
                self._push(self.now + delay, _Kind.ANSWER, peer.index, -1, (event.payload, report))
        elif event.kind is _Kind.ANSWER:
            poll_id, report = event.payload
            if node.poll_id == poll_id:
                node.poll_id = None
                machine.peer_report(self.now, report.role, report.lease_remaining, report.priority,
                                    report.peer_lease_remaining, node.poll_sent_at)  # fmt: skip
        elif event.kind is _Kind.TIMEOUT:
            if node.poll_id == event.payload:
                node.poll_id = None
                machine.peer_unreachable(self.now)
        elif event.kind is _Kind.FRAME:
            node.seen.add(event.payload)
            machine.master_frame_heard(self.now)
        else:
            machine.frame_heard(self.now)

    def _poll(self, node: _Node, peer: _Node) -> None:
        self.ids += 1
        node.poll_id = self.ids
        node.poll_sent_at = self.now
        delay = self._net(node.index, peer.index)
        if delay is not None:
            self._push(self.now + delay, _Kind.ARRIVE, peer.index, -1, self.ids)
        self._push(self.now + POLL_TIMEOUT, _Kind.TIMEOUT, node.index, node.incarnation, self.ids)
        self._push(self.now + POLL_EVERY, _Kind.POLL, node.index, node.incarnation)

    def _after_input(self, node: _Node) -> None:
        """The shell after each input: log changes, send a due keep-alive, re-arm the timer."""
        machine = node.machine
        assert machine is not None
        self._note_changes(node)
        # A keener shell than the gateway's, which sends one when ``handle_timer`` asks: a
        # due keep-alive goes out after any input (the same question, asked more often).
        machine.keepalives.clear()
        due = self.now >= node.busy_until and machine.keepalive_due(self.now)
        if due and machine.may_transmit(self.now):
            self._transmit(node)
        self._arm(node)

    def _note_changes(self, node: _Node) -> None:
        assert node.machine is not None
        for change in node.machine.drain_changes():
            if change.role is Role.ACTIVE:
                self.ids += 1
                node.reign, node.seen_at_takeover = self.ids, frozenset(node.seen)
                node.took_over_at = change.at
            else:
                node.reign = None

    def _transmit(self, node: _Node) -> None:
        machine, peer = node.machine, self.nodes[1 - node.index]
        assert machine is not None and machine.may_transmit(self.now)
        self._check_exclusion()
        machine.transmitted(self.now)
        self._note_changes(node)
        self._push(
            self.now + self.rng.uniform(0, BUS_DELAY), _Kind.FRAME, peer.index, -1, node.reign
        )
        if self.rng.random() < 0.8:  # the slave answers; both gateways hear it
            for listener in self.nodes:
                at = self.now + self.rng.uniform(0.01, BUS_DELAY)
                self._push(at, _Kind.SLAVE, listener.index, -1)

    def _check_exclusion(self) -> None:
        a, b = self.nodes
        if not all(n.machine is not None and not n.frozen for n in (a, b)):
            return
        assert a.machine is not None and b.machine is not None
        if a.machine.may_transmit(self.now) and b.machine.may_transmit(self.now):
            assert a.reign not in b.seen_at_takeover, f"B overlapped A's heard reign at {self.now}"
            assert b.reign not in a.seen_at_takeover, f"A overlapped B's heard reign at {self.now}"

    # -- rules --------------------------------------------------------------------------

    @rule(dt=st.floats(0.01, 3.0))
    def advance(self, dt: float) -> None:
        self._run_until(self.now + dt)

    @rule(index=st.sampled_from([0, 1]))
    def master_request(self, index: int) -> None:
        node = self.nodes[index]
        if node.machine is not None and not node.frozen and node.machine.may_transmit(self.now):
            self._transmit(node)
            self._arm(node)

    @rule(index=st.sampled_from([0, 1]))
    def freeze(self, index: int) -> None:
        node = self.nodes[index]
        if node.machine is not None:
            node.frozen = True

    @rule(index=st.sampled_from([0, 1]), frames_first=st.booleans())
    def resume(self, index: int, frames_first: bool) -> None:
        node = self.nodes[index]
        if node.machine is None or not node.frozen:
            return
        node.frozen = False
        machine = node.machine
        if machine.keepalive_due(self.now) and machine.may_transmit(self.now):
            self._transmit(node)  # it was about to send: the lease check comes first
        backlog, node.backlog = node.backlog, []
        if frames_first:
            backlog.sort(key=lambda e: e.kind not in (_Kind.FRAME, _Kind.SLAVE))
        for event in backlog:
            if event.kind is _Kind.TICK and event.payload != node.tick_gen:
                continue
            self._deliver(node, event)
            self._after_input(node)
            self._check_exclusion()
        self._arm(node)

    @rule(index=st.sampled_from([0, 1]), seconds=st.floats(0.5, 4.0), frames_first=st.booleans())
    def pause(self, index: int, seconds: float, frames_first: bool) -> None:
        """SIGSTOP, time passes, SIGCONT."""
        node = self.nodes[index]
        if node.machine is None or node.frozen:
            return
        node.frozen = True
        self._run_until(self.now + seconds)
        self.resume(index, frames_first)

    @rule(index=st.sampled_from([0, 1]), seconds=st.floats(0.1, 3.0))
    def hold_the_line(self, index: int, seconds: float) -> None:
        """The line waits for a slave's answer: no keep-alive can go out meanwhile."""
        self.nodes[index].busy_until = self.now + seconds

    @rule(index=st.sampled_from([0, 1]))
    def kill(self, index: int) -> None:
        node = self.nodes[index]
        node.machine, node.frozen, node.backlog, node.reign = None, False, [], None

    @rule(index=st.sampled_from([0, 1]))
    def restart(self, index: int) -> None:
        if self.nodes[index].machine is None:
            self._boot(self.nodes[index])

    @rule(up_ab=st.booleans(), up_ba=st.booleans(), loss=st.sampled_from([0.0, 0.3, 1.0]),
          slow=st.booleans())  # fmt: skip
    def network(self, up_ab: bool, up_ba: bool, loss: float, slow: bool) -> None:
        self.links = {(0, 1): up_ab, (1, 0): up_ba}
        self.loss = loss
        self.net_delay = 0.5 if slow else 0.05

    @rule()
    def kill_the_active_on_a_fine_network(self) -> None:
        """Liveness: the standby takes over within lease + takeover_after + one stagger."""
        if sorted(_roles(self.nodes)) != [Role.ACTIVE, Role.STANDBY]:
            return
        self.network(True, True, 0.0, slow=False)
        active = next(n for n in self.nodes if _roles((n,)) == [Role.ACTIVE])
        survivor = self.nodes[1 - active.index]
        killed_at = self.now
        self.kill(active.index)
        self._run_until(killed_at + LIVENESS_BOUND)
        assert survivor.machine is not None and survivor.machine.role is Role.ACTIVE
        assert survivor.took_over_at is not None
        assert killed_at < survivor.took_over_at <= killed_at + LIVENESS_BOUND

    @invariant()
    def one_writer(self) -> None:
        self._check_exclusion()


def _roles(nodes: tuple[_Node, ...]) -> list[Role]:
    """The roles of the alive, unfrozen nodes."""
    return [n.machine.role for n in nodes if n.machine is not None and not n.frozen]


def _pair_settings(examples: int) -> settings:
    return settings(
        max_examples=examples,
        stateful_step_count=40,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
    )


class TestPairOnOneBus(PairOnOneBus.TestCase):  # type: ignore[misc,valid-type]
    """A short run in the fast tier; the deep one below runs with the slow tests."""

    settings = _pair_settings(100)


@pytest.mark.slow
class TestPairOnOneBusDeep(PairOnOneBus.TestCase):  # type: ignore[misc,valid-type]
    """1,000 sequences (``REDUNDANCY_EXAMPLES``): about 20 s on two quiet cores."""

    settings = _pair_settings(int(os.environ.get("REDUNDANCY_EXAMPLES", "1000")))
