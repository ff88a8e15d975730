"""Learned response timing with literal times: the estimator alone, and the line core
driven against slaves of stated timing (no event loop, no port, no sleeping)."""

from __future__ import annotations

import random
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.config import LineConfig, build_config
from gateway.core.framing import RTU, mbap_framing
from gateway.core.line import LineCore, LineRequest
from gateway.core.line.response_timing import EVIDENCE, FLOOR_S, ResponseTiming
from gateway.core.outcome import Outcome
from gateway.core.rtu import encode_rtu
from gateway.core.timing import character_time
from tests.helpers import read
from tests.line_harness import DeafWhileBusyLine, LineHarness

SLAVE = 1


def answer(slave: int = SLAVE, quantity: int = 2) -> bytes:
    return encode_rtu(slave, bytes((3, 2 * quantity)) + bytes(2 * quantity))


def default_line(baudrate: int, **settings: Any) -> LineConfig:
    """A line as the configuration file makes it at defaults (``timeout = "auto"``)."""
    table = {"device": "/dev/null", "baudrate": baudrate, **settings}
    return build_config({"lines": {"a": table}}).lines[0]


class Bus(LineHarness):
    """A line core and one slave whose turnaround each test states per request."""

    def __init__(self, config: LineConfig) -> None:
        super().__init__(LineCore(config, -1.0))
        self.char = character_time(config.baudrate, config.data_bits, config.parity, 1)
        self.now = 0.0
        self.timeouts = 0

    def poll(self, turnaround: float | None, slave: int = SLAVE) -> tuple[str, float]:
        """One read; the slave answers ``turnaround`` after the request (``None``: never).
        Returns the outcome and when the master got it."""
        request = self.submit(slave, read(0, 2), self.now)
        sent = self.frames()
        assert len(sent) == 1
        frame = answer(slave)
        arrival = None
        if turnaround is not None:
            arrival = self.now + len(sent[0]) * self.char + turnaround + len(frame) * self.char
        at = self.now
        while request in self.unanswered():
            deadline = self.core.get_timer()
            assert deadline is not None
            if arrival is not None and arrival < deadline:
                at = arrival
                self.receive(frame, arrival)
                arrival = None
                continue
            before = len(self.notes_of_timeouts())
            at = self.timer()
            self.timeouts += len(self.notes_of_timeouts()) - before
            self.frames()  # a retry's frame: the slave answers the first one only
        _, outcome = self.answer_of(request)
        if arrival is not None:
            at = max(at, arrival)  # the answer still comes: the next request waits for it
            self.receive(frame, arrival)
        self.now = at + 0.01
        return outcome, at

    def notes_of_timeouts(self) -> list[Any]:
        return [n for n in self.core.notes if n.event.value == "timeout"]


# ------------------------------------------------------------------ the estimator alone


def timing(**settings: Any) -> ResponseTiming:
    config = LineConfig(name="t", device="/dev/null", learn_timeouts=True, **settings)
    return ResponseTiming(config, RTU, character_time(19200, 8, "N", 1))


def test_first_contact_waits_initial_timeout_and_retries_back_off_to_max_timeout() -> None:
    learned = timing()
    assert [learned.wait(SLAVE, 3, attempt) for attempt in (1, 2, 3)] == [1.0, 2.0, 3.0]
    learned.answered(SLAVE, 3, 0.005)
    assert learned.wait(SLAVE, 3, 1) == 1.0  # one fast answer is no evidence: still initial
    for _ in range(EVIDENCE - 1):
        learned.answered(SLAVE, 3, 0.005)
    assert learned.wait(SLAVE, 3, 1) == FLOOR_S  # the floor, not 7.5 ms
    assert learned.wait(SLAVE, 3, 2) == 2 * FLOOR_S
    assert learned.wait(SLAVE, 4, 1) == 1.0  # a function never heard from
    assert learned.wait(2, 3, 1) == 1.0  # a slave never heard from


def test_a_one_in_ten_slow_slave_keeps_a_bound_that_covers_its_slow_answers() -> None:
    learned = timing()
    for index in range(2000):
        learned.answered(SLAVE, 3, 0.5 if index % 10 == 0 else 0.005)
        assert learned.wait(SLAVE, 3, 1) > 0.5


def test_a_late_answer_widens_the_bound() -> None:
    learned = timing()
    for _ in range(50):
        learned.answered(SLAVE, 3, 0.005)
    learned.late(SLAVE, 3, 0.4)
    assert learned.wait(SLAVE, 3, 1) >= 0.4


def test_a_number_or_a_slave_timeouts_entry_is_fixed() -> None:
    learned = timing(slave_timeouts={2: 0.7})
    learned.answered(2, 3, 0.005)
    assert learned.wait(2, 3, 1) == learned.wait(2, 3, 2) == 0.7
    assert learned.learned(2, 3) is None
    fixed = ResponseTiming(LineConfig(name="t", device="/dev/null", timeout=0.4), RTU, 0.0)
    assert fixed.deadline(SLAVE, read(0, 2), 2, 10.0) == 10.4


def test_tcp_lines_learn_per_line() -> None:
    config = LineConfig(name="t", device="/dev/null", kind="tcp", learn_timeouts=True)
    learned = ResponseTiming(config, mbap_framing(), 0.0)
    for _ in range(EVIDENCE):
        learned.answered(1, 3, 0.3)
    assert learned.wait(2, 3, 1) == learned.wait(1, 3, 1) == pytest.approx(0.45)
    assert learned.slave_timeout(7) == pytest.approx(0.45)


@settings(max_examples=200, deadline=None)
@given(
    events=st.lists(
        st.tuples(st.booleans(), st.integers(1, 3), st.integers(1, 6), st.floats(0.0, 20.0)),
        max_size=60,
    ),
    slave=st.integers(1, 3),
    function=st.integers(1, 6),
    attempt=st.integers(1, 5),
    quantity=st.integers(1, 125),
    max_timeout=st.floats(0.05, 5.0),
)
def test_an_attempt_waits_its_answer_plus_a_bound_within_floor_and_max_timeout(
    events: list[tuple[bool, int, int, float]],
    slave: int,
    function: int,
    attempt: int,
    quantity: int,
    max_timeout: float,
) -> None:
    learned = timing(max_timeout=max_timeout)
    for late, event_slave, event_function, turnaround in events:
        if late:
            learned.late(event_slave, event_function, turnaround)
        else:
            learned.answered(event_slave, event_function, turnaround)
    pdu = struct.pack(">BHH", function, 0, quantity)
    answer_time = learned.answer_time(pdu)
    deadline = learned.deadline(slave, pdu, attempt, 100.0)
    assert learned.expected_at == 100.0 + answer_time
    waited = deadline - learned.expected_at
    assert min(FLOOR_S, max_timeout) - 1e-9 <= waited <= max_timeout + 1e-9
    assert deadline - 100.0 >= answer_time  # never below the answer's own transmission


# ------------------------------------------------------------------ the line core


def test_a_bimodal_slave_gets_no_timeout_after_warm_up_at_defaults() -> None:
    """5 ms, but 0.5 s on 10 % of requests, the first-ever one slow: after 30 requests of
    warm-up, no timeout and no exception."""
    bus = Bus(default_line(19200))
    chance = random.Random(22)
    failed_after_warm_up = 0
    for index in range(400):
        slow = index == 0 or chance.random() < 0.1
        if index == 30:
            bus.timeouts = 0
        outcome, _ = bus.poll(0.5 if slow else 0.005)
        if index >= 30 and outcome is not Outcome.OK:
            failed_after_warm_up += 1
    assert bus.timeouts == 0
    assert failed_after_warm_up == 0


@pytest.mark.parametrize("baudrate", [19200, 38400, 115200])
def test_a_learned_slave_that_dies_gets_its_0x0b_before_a_1_s_master_timeout(
    baudrate: int,
) -> None:
    bus = Bus(default_line(baudrate))
    for _ in range(50):
        assert bus.poll(0.005)[0] is Outcome.OK
    asked_at = bus.now
    outcome, answered_at = bus.poll(None)
    assert outcome is Outcome.TARGET_FAILED
    assert answered_at - asked_at < 1.0
    assert bus.timeouts == 2  # the attempt and its retry, backed off


def test_a_late_answer_on_the_line_widens_the_slave_s_bound() -> None:
    bus = Bus(default_line(19200, retries=0))
    for _ in range(50):
        bus.poll(0.005)
    assert bus.core.timing.learned(SLAVE, 3) == FLOOR_S
    request = bus.submit(SLAVE, read(0, 2), bus.now)
    bus.frames()
    bus.timer()  # no answer within the learned bound
    assert bus.answer_of(request)[1] is Outcome.TARGET_FAILED
    bus.receive(answer(), bus.now + 0.4)  # there it is, late
    bound = bus.core.timing.learned(SLAVE, 3)
    assert bound is not None and bound >= 0.4


def test_a_reload_that_keeps_the_line_keeps_what_was_learned() -> None:
    bus = Bus(default_line(19200))
    bus.poll(0.2)
    learned = bus.core.timing.learned(SLAVE, 3)
    bus.core.reconfigure(default_line(19200, retries=2), bus.now)
    assert bus.core.timing.learned(SLAVE, 3) == learned
    assert LineCore(default_line(19200), 0.0).timing.learned(SLAVE, 3) is None


def test_the_learned_timeouts_are_exported_per_slave_at_scrape_time() -> None:
    from prometheus_client import CollectorRegistry

    from gateway.metrics import GatewayMetrics

    registry = CollectorRegistry()
    metrics = GatewayMetrics(registry)
    bus = Bus(default_line(19200))
    for _ in range(EVIDENCE):
        bus.poll(0.2)
    core = bus.core
    metrics.set_response_timeouts("a", lambda: core.timing.by_slave(core.health.slaves))
    name = "modbus_gateway_slave_response_timeout_seconds"
    exported = registry.get_sample_value(name, {"line": "a", "unit": "1"})
    assert exported == core.timing.learned(SLAVE, 3) == pytest.approx(0.3, abs=0.01)
    assert registry.get_sample_value(name, {"line": "a", "unit": "2"}) is None


def closed_loop(line: DeafWhileBusyLine, units: list[int], polls: int) -> list[Outcome]:
    """One master reading 10 registers of ``units`` in turn, the next as soon as answered."""
    outcomes: list[Outcome] = []
    turn = iter(range(1, polls))

    def again(_request: LineRequest, outcome: Outcome) -> None:
        outcomes.append(outcome)
        index = next(turn, None)
        if index is not None:
            line.submit("m", units[index % len(units)], read(100 * index % 9000, 10))

    line.on_answer = again
    line.submit("m", units[0], read(0, 10))
    line.run(3600.0)
    assert len(outcomes) == polls
    assert line.wrong == 0
    return outcomes


@pytest.mark.parametrize("seed", range(12))
def test_a_soft_plc_fast_at_first_then_anywhere_in_its_cycle_is_never_timed_out(
    seed: int,
) -> None:
    """One device answering unit ids 1-4: its first 5 answers (over all four) come within
    40 ms, every later one anywhere in 20-480 ms (it scans its port once per cycle). Polled
    round-robin 200 times at 115200 baud at defaults: a bound learned from the first fast
    answers would time out the slow ones; learning waits for evidence first."""
    draw = random.Random(seed)
    heard = iter(range(10**6))

    def turnaround(_slave: int, _pdu: bytes, _now: float) -> float:
        return draw.uniform(0.0, 0.04) if next(heard) < 5 else draw.uniform(0.02, 0.48)

    config = default_line(115200)
    line = DeafWhileBusyLine(LineCore(config, -1.0), character_time(115200, 8, "N", 1), turnaround)
    outcomes = closed_loop(line, [1, 2, 3, 4], 200)
    assert outcomes.count(Outcome.OK) == 200, outcomes


def test_a_slave_that_turns_slow_costs_at_most_two_exceptions() -> None:
    """A slave answering in 10 ms turns to 400 ms after 60 polls: its bound grows at once
    on the late answer; at most 2 exceptions after the change, none in its last 20 polls."""
    polls = iter(range(10**6))

    def turnaround(_slave: int, _pdu: bytes, _now: float) -> float:
        return 0.010 if next(polls) < 60 else 0.400

    config = default_line(19200)
    line = DeafWhileBusyLine(LineCore(config, -1.0), character_time(19200, 8, "N", 1), turnaround)
    outcomes = closed_loop(line, [1], 150)
    before, after = outcomes[:60], outcomes[60:]
    assert set(before) == {Outcome.OK}
    assert sum(outcome is not Outcome.OK for outcome in after) <= 2, after
    assert set(after[-20:]) == {Outcome.OK}, after
