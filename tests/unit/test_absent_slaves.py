"""Absent addresses at default (learned) timing, with literal times: masters polling
addresses where no slave answers must not starve a master polling a live slave.

A first contact with a slave never heard from waits ``initial_timeout`` (1 s). Masters
rotating over absent addresses make every request such a first contact, so isolating
each address after its misses never comes into play: the line's fair share by wire time
alone left a master polling a live slave one transaction per absent attempt (its next
request comes a few milliseconds after its answer, when the next 1 s attempt has begun).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest

from gateway.config import LineConfig, build_config
from gateway.core.line import LineCore, LineRequest
from gateway.core.line.health import FIRST_CONTACT_QUIET_S
from gateway.core.outcome import Outcome, SlaveState
from gateway.core.rtu import encode_rtu
from gateway.core.timing import character_time

BAUD = 19200
LIVE = 1
ABSENT = list(range(100, 248))
PDU = struct.pack(">BHH", 3, 0, 2)
ANSWER = encode_rtu(LIVE, bytes((3, 4)) + bytes(4))
TURNAROUND = 0.005  # the live slave's
THINK = 0.003  # a master's next request after its answer
REFUSED_PAUSE = 0.1  # a master's next request after an exception


def line_config(**settings: object) -> LineConfig:
    """A line as the configuration file makes it at defaults (``timeout = "auto"``)."""
    return build_config(
        {"lines": {"a": {"device": "/dev/null", "baudrate": BAUD, **settings}}}
    ).lines[0]


@dataclass
class Plant:
    """A line core, one live slave, and closed-loop masters (one request at a time each)."""

    config: LineConfig
    core: LineCore = field(init=False)
    char: float = field(init=False)
    now: float = 0.0
    due: dict[str, float] = field(default_factory=dict)  # master -> its next request
    answer_at: float | None = None  # the live slave's answer on its way
    outcomes: dict[str, list[tuple[float, float, Outcome]]] = field(default_factory=dict)
    sent: list[tuple[float, int]] = field(default_factory=list)
    next_unit: dict[str, int] = field(default_factory=dict)
    looping: set[str] = field(default_factory=set)  # masters that poll on after an answer
    in_step: bool = False  # every absent master rotates from unit 100 (as the bench's do)
    live_last: bool = False  # the live master asks again a hair after every other master

    def __post_init__(self) -> None:
        self.core = LineCore(self.config, -1.0)
        self.core.port_opened(-1.0)
        self.char = character_time(BAUD, self.config.data_bits, self.config.parity, 1)

    def reply(self, master: str, submitted: float) -> Callable[[bytes, str], None]:
        def record(_pdu: bytes, outcome: str) -> None:
            kind = Outcome(outcome)
            self.outcomes.setdefault(master, []).append((submitted, self.now, kind))
            if master in self.looping:
                pause = THINK if kind is Outcome.OK else REFUSED_PAUSE + self.skew(master)
                self.due[master] = self.now + pause

        return record

    def submit(self, master: str, slave: int) -> LineRequest:
        request = LineRequest(slave, PDU, master, self.reply(master, self.now))
        self.core.submit(request, self.now)
        return request

    def start(self, absent_masters: int, live_at: float = 0.0) -> None:
        """``absent_masters`` masters rotating over the absent units from the start, one
        polling the live slave from ``live_at``, all in a loop."""
        for index in range(absent_masters):
            self.due[f"a{index}"] = self.skew(f"a{index}")
        self.due["live"] = live_at
        self.looping.update(self.due)

    def skew(self, master: str) -> float:
        """Masters are not in step: each pauses a little longer than the one before (in
        step, the same, the live master last when ``live_last``)."""
        if master == "live":
            return 0.0001 if self.live_last else 0.0
        return 0.0 if self.in_step else 0.0007 * (1 + int(master[1:]))

    def unit_for(self, master: str) -> int:
        if master == "live":
            return LIVE
        index = self.next_unit.get(master, 0 if self.in_step else 18 * int(master[1:]))
        self.next_unit[master] = index + 1
        return ABSENT[index % len(ABSENT)]

    def run(self, until: float) -> None:
        """Drive the core: masters' requests, the live slave's answers, the core's timer."""
        core = self.core
        while self.now < until:
            events: list[tuple[float, int]] = []
            if self.due:
                events.append((min(self.due.values()), 0))
            timer = core.get_timer()
            if timer is not None:
                events.append((timer, 1))
            if self.answer_at is not None:
                events.append((self.answer_at, 2))
            if not events:
                self.now = until
                return
            at, kind = min(events)
            if at > until:
                self.now = until
                return
            self.now = max(self.now, at)
            if kind == 0:
                master = min(self.due, key=self.due.__getitem__)
                del self.due[master]
                self.submit(master, self.unit_for(master))
            elif kind == 1:
                core.handle_timer(self.now)
            else:
                self.answer_at = None
                core.receive(ANSWER, self.now)
            self.pump()

    def pump(self) -> None:
        core = self.core
        for transmit in core.transmits:
            self.sent.append((self.now, transmit.request.slave))
            if transmit.request.slave == LIVE:
                tx = len(transmit.frame) * self.char
                self.answer_at = self.now + tx + TURNAROUND + len(ANSWER) * self.char
        core.transmits.clear()
        deliveries, core.deliveries = core.deliveries, []
        for delivery in deliveries:
            delivery.request.reply(delivery.pdu, delivery.outcome)

    def transaction_s(self) -> float:
        return (8 + len(ANSWER)) * self.char + TURNAROUND

    def ok(self, master: str) -> int:
        return sum(1 for _, _, kind in self.outcomes.get(master, []) if kind is Outcome.OK)


def test_a_live_slaves_master_keeps_its_fair_share_among_masters_scanning_absent_units() -> None:
    """8 masters rotating over absent units and 1 polling a live slave: the live master
    gets at least 1/9 of the wire (it got 0.03x that while every first contact held the
    line 1 s: one live transaction per absent attempt at best)."""
    plant = Plant(line_config())
    plant.start(8)
    window = 30.0
    plant.run(window)
    share = plant.ok("live") * plant.transaction_s() / window
    assert share >= 1 / 9, share


@pytest.mark.parametrize(("in_step", "live_last"), [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("live_at", [0.05, 0.5, 1.5, 3.25])
def test_a_live_slave_first_polled_once_units_are_absent_gets_its_fair_share(
    live_at: float, in_step: bool, live_last: bool
) -> None:
    """The live slave is first asked after absent units missed: its first contact is a
    probe among theirs, waits for the next time the line is free of them, and goes first
    (its master used the line least); answered, it is polled as usual. Masters whose
    pause after a 0x0B matches the line's quiet before a probe must not lock it out."""
    plant = Plant(line_config(), in_step=in_step, live_last=live_last)
    plant.start(8, live_at)
    window = 30.0
    plant.run(window)
    share = plant.ok("live") * plant.transaction_s() / (window - live_at)
    assert share >= 1 / 9, share


def test_masters_polling_absent_units_are_answered_within_the_first_contact_wait() -> None:
    """The absent units' masters are not starved either: each request is answered 0x0B
    once it could have gone as a probe, or after its own (6 s at worst, before)."""
    plant = Plant(line_config())
    plant.start(8)
    plant.run(20.0)
    longest = 0.0
    for index in range(8):
        for submitted, answered, kind in plant.outcomes[f"a{index}"]:
            assert kind is Outcome.TARGET_FAILED
            longest = max(longest, answered - submitted)
    # In the lane: a probe's longest hold (its wait, two longest frames) and the quiet
    # before the next; then, if it went as a probe itself, its own attempt.
    attempt = 1.0 + 2 * 256 * plant.char
    assert longest <= attempt + FIRST_CONTACT_QUIET_S + attempt, longest


def test_a_request_to_a_slave_never_heard_from_is_not_retried() -> None:
    """No answer ever seen: a retry would hold the line 2 s more for nothing. One frame,
    and 0x0B after the first-contact wait."""
    plant = Plant(line_config())
    plant.submit("m", 100)
    plant.pump()
    plant.run(5.0)
    assert [slave for _, slave in plant.sent] == [100]
    [(_, answered, kind)] = plant.outcomes["m"]
    assert kind is Outcome.TARGET_FAILED
    assert 1.0 < answered < 1.05


def test_a_slow_slave_never_heard_from_is_served_at_defaults_beside_absent_units() -> None:
    """The first-contact rule stands among absent addresses: a slave that needs 0.8 s,
    asked for the first time just after an absent unit missed, is still waited for
    ``initial_timeout`` once the line is quiet, and its answer is taken."""
    plant = Plant(line_config())
    plant.submit("scan", 100)
    plant.pump()
    plant.run(1.05)  # unit 100 missed its first contact: it is absent
    assert plant.outcomes["scan"][0][2] is Outcome.TARGET_FAILED
    asked = plant.now
    request = plant.submit("m", 2)
    plant.pump()
    core = plant.core
    while not plant.sent or plant.sent[-1][1] != 2:
        timer = core.get_timer()
        assert timer is not None
        plant.now = timer
        core.handle_timer(timer)
        plant.pump()
    sent_at = plant.sent[-1][0]
    assert sent_at <= asked + FIRST_CONTACT_QUIET_S + 1e-9
    answer = encode_rtu(2, bytes((3, 4)) + bytes(4))
    core.receive(answer, sent_at + 0.8)
    plant.now = sent_at + 0.8
    deliveries = core.deliveries
    assert [(d.request, d.outcome) for d in deliveries] == [(request, Outcome.OK)]


def test_masters_asking_in_the_same_moment_compete_for_a_free_probe() -> None:
    """A free probe does not go to the first master to ask once the line is quiet (the
    masters whose requests were answered 0x0B together ask again together, the same one
    first each time): a first contact waits ``FIRST_CONTACT_QUIET_S`` itself, and the
    master that used the line least goes."""
    plant = Plant(line_config())
    plant.submit("scan", 100)
    plant.pump()
    plant.run(1.05)  # unit 100 missed its first contact: "scan" paid 1 s of wire
    plant.now = 2.0  # the line has been quiet long since
    plant.submit("scan", 101)
    plant.pump()
    plant.now = 2.001
    plant.submit("live", LIVE)
    plant.pump()
    core = plant.core
    while len(plant.sent) == 1:
        timer = core.get_timer()
        assert timer is not None
        plant.now = timer
        core.handle_timer(timer)
        plant.pump()
    assert plant.sent[1][1] == LIVE
    assert plant.sent[1][0] == pytest.approx(2.001 + FIRST_CONTACT_QUIET_S)


def test_with_isolation_turned_off_first_contacts_are_queued_as_usual_again() -> None:
    """A reload that turns isolation off (``dead_after = 0``) forgets the absent slaves:
    a first contact is queued for the fair order again, not made a probe."""
    plant = Plant(line_config())
    plant.submit("scan", 100)
    plant.pump()
    plant.run(1.05)
    assert plant.core.health.absent == {100}
    plant.core.reconfigure(line_config(dead_after=0), plant.now)
    plant.submit("live", LIVE)
    plant.pump()
    assert plant.sent[-1] == (plant.now, LIVE)


def test_a_master_waiting_through_a_probe_goes_before_the_next_one() -> None:
    """A poll that came while a probe held the line goes when it ends, even when the lane's
    share has paid its debt by then: the share's next probe goes after it (it used to
    follow at once, and the poll waited through two probes)."""
    plant = Plant(line_config())
    plant.submit("live", LIVE)  # the live slave, heard before any address is absent
    plant.pump()
    plant.run(0.05)
    plant.submit("scan", 100)
    plant.pump()
    plant.run(1.2)
    plant.submit("scan", 101)
    plant.pump()
    plant.run(4.0)  # both missed: suspect, and the lane's share is in debt
    core = plant.core
    assert core.slave_state(100) is core.slave_state(101) is SlaveState.SUSPECT
    start = core.lane.credit_time() - 0.5  # paid off half a second into the next probe

    def probe(master: str, slave: int, count: int) -> None:
        # Another count than the lost reads': their late-answer windows do not hold it.
        pdu = struct.pack(">BHH", 3, 0, count)
        core.submit(LineRequest(slave, pdu, master, plant.reply(master, plant.now)), plant.now)
        plant.pump()

    plant.run(start)
    probe("scan", 100, 3)  # the share in debt, nothing else waits: it goes free
    assert plant.sent[-1] == (start, 100)
    plant.run(start + 0.1)
    probe("scan2", 101, 4)  # waits in the lane for the share
    plant.run(start + 0.2)
    plant.submit("live", LIVE)  # a poll, while the probe holds the line
    plant.pump()
    plant.run(start + 3.0)
    assert [slave for _, slave in plant.sent[-3:]] == [100, LIVE, 101]
