"""Agent mode in the line core: poll blocks, answers from memory and their freshness contract.

A simulated serial line of slaves that hold registers (reads, FC 6 and FC 16 writes),
driven with literal times. The contract checked throughout: a read answered from memory
is byte for byte what the slave sent for those registers, never older than the block's
``max_age`` (counted from the poll's frame), and never older than a change submitted
before the read.
"""

from __future__ import annotations

import functools
import itertools
import random
from collections.abc import Hashable
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.config import LineConfig, PollConfig
from gateway.core.line import INFINITY, LineCore, LineRequest
from gateway.core.line.polling import AGE_NEVER, PollPlan, changed_range
from gateway.core.outcome import BlockState, Outcome, SlaveState
from gateway.core.rtu import encode_rtu
from tests.helpers import read
from tests.line_harness import SimulatedTime, new_core

CHAR = 11 / 19200  # seconds a character takes at 19200 baud, 8N1 plus start


def block(
    slave: int = 1,
    function: int = 3,
    address: int = 0,
    count: int = 10,
    every: float = 1.0,
    max_age: float | None = None,
) -> PollConfig:
    return PollConfig(
        slave,
        function,
        address,
        count,
        every,
        3.0 * every if max_age is None else max_age,
        "t",
        slave,
    )


def write(address: int, value: int) -> bytes:
    return bytes((6, address >> 8, address & 0xFF, value >> 8, value & 0xFF))


class RegisterLine(SimulatedTime):
    """A core on a 19200-baud line of slaves that hold 100 registers each (also as coils:
    coil ``a`` is register ``a``'s lowest bit) and answer after ``turnaround`` seconds,
    or not at all while ``silent``."""

    def __init__(self, blocks: tuple[PollConfig, ...], **settings: object) -> None:
        super().__init__()
        config = LineConfig(
            name="t",
            device="/dev/null",
            baudrate=19200,
            polls=blocks,
            **settings,  # type: ignore[arg-type]
        )
        self.core: LineCore = new_core(config, 0.0)
        self.registers: dict[int, list[int]] = {1: list(range(100)), 2: list(range(100))}
        self.turnaround = 0.01
        self.silent: set[int] = set()
        self.exceptions: set[int] = set()
        self.frames: list[bytes] = []
        self.answers: list[tuple[LineRequest, bytes, Outcome, float]] = []
        self.core.port_opened(0.0)
        self._pump()

    def submit(self, slave: int, pdu: bytes, master: Hashable = "m") -> LineRequest:
        request = LineRequest(slave, pdu, master, lambda _pdu, _outcome: None, slave == 0)
        self.core.submit(request, self.now)
        self._pump()
        return request

    def answer_of(self, request: LineRequest) -> tuple[bytes, Outcome]:
        found = [(pdu, outcome) for r, pdu, outcome, _ in self.answers if r is request]
        assert len(found) == 1, found
        return found[0]

    def polls(self) -> list[bytes]:
        return [frame for frame in self.frames if frame[1] in (1, 3) and len(frame) == 8]

    def _pump(self) -> None:
        core = self.core
        while core.transmits or core.deliveries:
            transmits, core.transmits = core.transmits, []
            for transmit in transmits:
                self.frames.append(transmit.frame)
                self._slave_hears(transmit.frame)
            deliveries, core.deliveries = core.deliveries, []
            for request, pdu, outcome, _wire in deliveries:
                self.answers.append((request, pdu, outcome, self.now))

    def _slave_hears(self, frame: bytes) -> None:
        slave, pdu = frame[0], frame[1:-2]
        end = self.now + len(frame) * CHAR
        if slave == 0:  # a broadcast write: every slave applies it, none answers
            for registers in self.registers.values():
                registers[(pdu[1] << 8) | pdu[2]] = (pdu[3] << 8) | pdu[4]
            return
        if slave in self.silent:
            return
        registers = self.registers[slave]
        function = pdu[0]
        address = (pdu[1] << 8) | pdu[2]
        if slave in self.exceptions:
            answer = bytes((function | 0x80, 4))
        elif function == 3:
            count = (pdu[3] << 8) | pdu[4]
            data = b"".join(registers[address + i].to_bytes(2, "big") for i in range(count))
            answer = bytes((3, len(data))) + data
        elif function == 1:
            count = (pdu[3] << 8) | pdu[4]
            bits = bytearray((count + 7) // 8)
            for i in range(count):
                if registers[address + i] & 1:
                    bits[i // 8] |= 1 << (i % 8)
            answer = bytes((1, len(bits))) + bytes(bits)
        elif function == 6:
            registers[address] = (pdu[3] << 8) | pdu[4]  # applied when the frame ends
            answer = pdu
        elif function == 16:
            count = (pdu[3] << 8) | pdu[4]
            for i in range(count):
                registers[address + i] = int.from_bytes(pdu[6 + 2 * i : 8 + 2 * i], "big")
            answer = pdu[:5]
        else:
            answer = bytes((function | 0x80, 1))
        wire = encode_rtu(slave, answer)
        arrives = end + self.turnaround + len(wire) * CHAR
        self.at(arrives, lambda: self.core.receive(wire, self.now))


def test_a_read_inside_a_fresh_block_is_answered_from_memory_byte_for_byte() -> None:
    line = RegisterLine((block(count=50),))
    line.run(0.5)
    assert len(line.polls()) == 1  # polled at once on start
    before = len(line.frames)
    request = line.submit(1, read(10, 5))
    assert len(line.frames) == before  # nothing on the wire
    pdu, outcome = line.answer_of(request)
    assert outcome is Outcome.MEMORY
    assert pdu == bytes((3, 10)) + b"".join(i.to_bytes(2, "big") for i in range(10, 15))


def test_a_coil_block_answers_any_sub_range_repacked_as_the_slave_would() -> None:
    line = RegisterLine((block(function=1, count=40),))
    line.registers[1] = [i % 3 for i in range(100)]  # odd values are coils that are on
    line.run(0.5)
    for address, count in [(0, 40), (3, 9), (17, 1), (31, 9)]:
        request = line.submit(1, read(address, count, 1))
        pdu, outcome = line.answer_of(request)
        assert outcome is Outcome.MEMORY
        bits = bytearray((count + 7) // 8)
        for i in range(count):
            if line.registers[1][address + i] & 1:
                bits[i // 8] |= 1 << (i % 8)
        assert pdu == bytes((1, len(bits))) + bytes(bits), (address, count)


def test_reads_outside_a_block_or_of_another_function_go_to_the_wire() -> None:
    line = RegisterLine((block(address=10, count=10, every=5.0),))
    line.run(0.5)
    for pdu in (read(5, 10), read(15, 10), read(10, 10, 4), read(10, 1, 1)):
        before = len(line.frames)
        request = line.submit(1, pdu)
        line.run(line.now + 0.2)
        assert len(line.frames) == before + 1
        assert line.answer_of(request)[1] is not Outcome.MEMORY


def test_the_plan_keeps_its_pace_and_measures_it() -> None:
    line = RegisterLine((block(every=0.5), block(slave=2, every=1.0)))
    line.run(10.1)  # each poll goes after the line's silence (t3.5, 1.8 ms)
    to_one = [frame for frame in line.polls() if frame[0] == 1]
    to_two = [frame for frame in line.polls() if frame[0] == 2]
    assert len(to_one) == 21 and len(to_two) == 11  # at 0, then every period up to 10 s
    periods = [b.period for b in line.core.plan.blocks]
    assert periods[0] == pytest.approx(0.5, abs=0.01)
    assert periods[1] == pytest.approx(1.0, abs=0.01)


def test_a_due_poll_goes_before_the_masters_waiting_requests_never_inside_a_transaction() -> None:
    line = RegisterLine((block(count=10, every=1.0),))
    line.turnaround = 0.2  # each transaction takes about 0.21 s
    line.run(0.99)  # just before the second poll is due
    requests = [line.submit(2, read(i), master=f"m{i}") for i in range(5)]
    line.run(3.0)
    poll = encode_rtu(1, read(0, 10))
    reads = [encode_rtu(2, read(i)) for i in range(5)]
    # The first read was on the wire when the poll fell due: the poll goes right after it,
    # before the four masters that were waiting.
    assert line.frames[:6] == [poll, reads[0], poll, *reads[1:4]]
    assert reads[4] in line.frames[6:8]  # behind the poll due at 2 s if that came first
    assert all(line.answer_of(request)[1] is Outcome.OK for request in requests)


def test_memory_answers_stop_at_max_age_and_the_wire_then_answers_0x0b() -> None:
    line = RegisterLine((block(count=10, every=1.0, max_age=2.5),), initial_timeout=0.3)
    line.run(0.5)
    last_poll_sent = 0.0
    line.silent.add(1)  # from now on the slave answers nothing
    line.run(2.49)
    served = line.submit(1, read(0, 2))
    assert line.answer_of(served)[1] is Outcome.MEMORY  # 2.49 s after the poll went
    line.run(2.51)
    late = line.submit(1, read(0, 2))
    line.run(5.0)
    assert line.now - last_poll_sent > 2.5
    pdu, outcome = line.answer_of(late)
    assert outcome is Outcome.TARGET_FAILED and pdu == bytes((0x83, 0x0B))
    assert [b.state(line.now) for b in line.core.plan.blocks] == [BlockState.FAILING]
    # No read was ever answered from memory with data older than max_age.
    for _request, _pdu, outcome, at in line.answers:
        if outcome is Outcome.MEMORY:
            assert at <= 2.5


def test_an_exception_to_a_poll_is_never_kept_and_marks_the_block_failing() -> None:
    line = RegisterLine((block(count=10),))
    line.exceptions.add(1)
    line.run(0.5)
    plan = line.core.plan
    assert plan.blocks[0].answer is None
    assert plan.blocks[0].state(line.now) is BlockState.FAILING
    request = line.submit(1, read(0))
    line.run(1.0)
    assert line.answer_of(request)[1] is Outcome.SLAVE_EXCEPTION
    assert plan.blocks[0].status_registers(line.now) == (AGE_NEVER, 2)


def test_a_read_after_a_write_sees_it_from_any_master() -> None:
    line = RegisterLine((block(count=10, every=5.0),))
    line.run(0.5)
    write_request = line.submit(1, write(3, 777), master="writer")
    reader = line.submit(1, read(0, 10), master="reader")  # submitted after the write
    assert reader not in [r for r, *_ in line.answers]  # not from memory: the write waits
    line.run(1.0)
    assert line.answer_of(write_request)[1] is Outcome.OK
    pdu, outcome = line.answer_of(reader)
    assert outcome is Outcome.OK and pdu[2 + 6 : 2 + 8] == (777).to_bytes(2, "big")
    # The block is polled again right after the write's answer, and serves the new value.
    polls_after_write = [f for f in line.frames[2:] if f == encode_rtu(1, read(0, 10))]
    assert polls_after_write
    again = line.submit(1, read(3), master="reader")
    assert line.answer_of(again) == (bytes((3, 2)) + (777).to_bytes(2, "big"), Outcome.MEMORY)


def test_a_write_outside_the_block_or_to_another_table_keeps_it_serving() -> None:
    line = RegisterLine((block(address=0, count=10, every=5.0),))
    line.run(0.5)
    line.submit(1, write(50, 1), master="writer")  # holding register 50: outside
    line.submit(1, bytes((5, 0, 3, 0xFF, 0)), master="writer")  # coil 3: another table
    request = line.submit(1, read(0, 10), master="reader")
    assert line.answer_of(request)[1] is Outcome.MEMORY
    line.submit(2, write(3, 1), master="writer")  # another slave
    request = line.submit(1, read(0, 10), master="reader")
    assert line.answer_of(request)[1] is Outcome.MEMORY


def test_a_broadcast_write_stops_memory_answers_until_the_blocks_are_polled_again() -> None:
    line = RegisterLine((block(count=10, every=5.0), block(slave=2, count=10, every=5.0)))
    line.run(0.5)
    line.submit(0, write(3, 9), master="writer")
    for slave in (1, 2):
        request = line.submit(slave, read(0), master="reader")
        assert request not in [r for r, *_ in line.answers]
    line.run(1.5)
    for slave in (1, 2):
        request = line.submit(slave, read(0), master="reader")
        assert line.answer_of(request)[1] is Outcome.MEMORY


def test_changed_range_names_the_table_and_range_of_every_write_function() -> None:
    assert changed_range(read(0)) is None
    assert changed_range(bytes((5, 0, 7, 0xFF, 0))) == ("coils", 7, 1)
    assert changed_range(bytes((15, 0, 7, 0, 12, 2, 0, 0))) == ("coils", 7, 12)
    assert changed_range(write(9, 1)) == ("holding_registers", 9, 1)
    assert changed_range(bytes((16, 0, 9, 0, 2, 4, 0, 1, 0, 2))) == ("holding_registers", 9, 2)
    assert changed_range(bytes((22, 0, 9, 0, 0xFF, 0, 0))) == ("holding_registers", 9, 1)
    rw = bytes((23, 0, 0, 0, 1, 0, 40, 0, 3, 6)) + bytes(6)
    assert changed_range(rw) == ("holding_registers", 40, 3)
    assert changed_range(bytes((8, 0, 1, 0, 0))) == ("*", 0, 65536)


def test_an_isolated_slaves_block_is_polled_at_the_lanes_pace() -> None:
    line = RegisterLine((block(count=10, every=0.2),), initial_timeout=0.1, probe_interval=1.0)
    line.silent.add(1)
    line.run(20.0)
    assert line.core.slave_state(1) is SlaveState.DOWN
    polls = line.polls()
    # Without isolation: one poll each 0.2 s (100). Isolated, the lane spaces them out.
    assert len(polls) < 40, len(polls)
    line.silent.clear()
    line.run(60.0)
    assert line.core.plan.blocks[0].state(line.now) is BlockState.FRESH


def test_a_reload_keeps_an_unchanged_blocks_memory_and_drops_a_removed_one() -> None:
    kept, dropped = block(count=10), block(slave=2, count=10)
    line = RegisterLine((kept, dropped))
    line.run(0.5)
    faster = block(count=10, every=0.5)
    line.core.reconfigure(
        LineConfig(name="t", device="/dev/null", baudrate=19200, polls=(faster,)), line.now
    )
    assert [b.spec for b in line.core.plan.blocks] == [faster]
    request = line.submit(1, read(0, 10))
    assert line.answer_of(request)[1] is Outcome.MEMORY
    request = line.submit(2, read(0, 10))
    line.run(line.now + 0.5)
    assert line.answer_of(request)[1] is Outcome.OK


def test_the_line_that_replaces_this_one_keeps_its_memory() -> None:
    line = RegisterLine((block(count=10),))
    line.run(0.5)
    handover = line.core.handover()
    config = LineConfig(name="t", device="/dev/null", baudrate=19200, polls=(block(count=10),))
    successor = new_core(config, line.now)
    successor.port_opened(line.now)
    successor.take_over(handover, line.now)
    request = LineRequest(1, read(0, 4), "m", lambda _p, _o: None)
    successor.submit(request, line.now)
    assert [d.outcome for d in successor.deliveries] == [Outcome.MEMORY]


def test_status_registers_say_age_in_tenths_and_state() -> None:
    plan = PollPlan([block(count=2, every=1.0, max_age=3.0)], 0.0)
    status = plan.blocks[0]
    assert status.status_registers(0.0) == (AGE_NEVER, 1)  # never polled: stale
    status.answer, status.polled_at = bytes((3, 4, 0, 1, 0, 2)), 10.0
    assert status.status_registers(12.34) == (23, 0)
    assert status.status_registers(13.5) == (35, 1)
    assert status.status_registers(10_000.0) == (AGE_NEVER, 1)
    status.failing = True
    assert status.status_registers(12.0) == (20, 2)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_no_read_returns_a_value_older_than_a_write_submitted_before_it(seed: int) -> None:
    """A writer counts register 3 up (one master: its writes keep their order); readers
    read it. A read from memory sees at least every write submitted before it."""
    rng = random.Random(seed)
    line = RegisterLine((block(count=10, every=rng.choice([0.05, 0.3, 1.0])),))
    line.turnaround = rng.uniform(0.002, 0.05)
    state = {"next": 1}
    checks: list[tuple[LineRequest, int, int]] = []
    written: dict[int, int] = {}

    def writer(name: str) -> None:
        value = state["next"]
        state["next"] += 1
        request = line.submit(1, write(3, value), master="writer")
        written[id(request)] = value

    def reader(name: str) -> None:
        # From memory: at least every write submitted before; from the wire (another
        # master's write may be sent after this read): every write answered before.
        answered = [written[id(r)] for r, _p, o, _t in line.answers if id(r) in written]
        submitted = state["next"] - 1
        request = line.submit(1, read(0, 10), master=name)
        checks.append((request, max(answered, default=0), submitted))

    for _ in range(80):
        when = rng.uniform(0.0, 8.0)
        act = rng.choice([writer, reader, reader])
        name = rng.choice(["a", "b", "c"])
        line.at(when, functools.partial(act, name))
    line.run(20.0)
    for request, answered, submitted in checks:
        pdu, outcome = line.answer_of(request)
        value = int.from_bytes(pdu[8:10], "big")
        if outcome is Outcome.MEMORY:
            assert value >= submitted, (value, submitted)
        elif outcome is Outcome.OK:
            assert value >= answered, (value, answered)


def test_a_plan_that_needs_the_whole_line_alternates_with_the_masters() -> None:
    line = RegisterLine((block(count=100, every=0.05),))  # each poll takes about 0.14 s
    requests = [line.submit(2, read(i), master=f"m{i % 3}") for i in range(10)]
    line.run(5.0)
    assert all(line.answer_of(request)[1] is Outcome.OK for request in requests)
    to_two = [i for i, frame in enumerate(line.frames) if frame[0] == 2]
    assert all(later - earlier == 2 for earlier, later in itertools.pairwise(to_two))


def test_a_stopped_line_polls_no_more_and_falls_idle() -> None:
    line = RegisterLine((block(count=10, every=0.2),), initial_timeout=1.0)
    line.silent.add(1)  # each poll waits out its timeout, longer than the period
    line.run(0.5)
    line.core.stop(line.now)
    sent = len(line.frames)
    line.run(5.0)
    assert len(line.frames) == sent  # the poll on the wire ended; no other went
    assert line.core.idle and line.core.get_timer() is None


def test_a_due_poll_goes_when_the_masters_turn_finds_only_the_lane_waiting() -> None:
    """Found by the polled line machine: a poll went first, so the next turn was the
    masters'; but all that waited was a silent slave's block poll in the isolated slaves'
    lane, off its credit. Nothing went, and the core asked for its timer at the other
    block's due time again and again (a spin) until the lane's credit came back."""
    line = RegisterLine(
        (block(slave=2, address=77, count=15, every=0.1), block(address=48, every=0.64)),
        timeout=0.2, retries=1, dead_after=3, probe_interval=0.5, probe_max_interval=1.0,
    )  # fmt: skip
    line.silent.add(2)
    line.submit(2, read(89, 6))
    line.submit(2, read(79, 3))
    stalled = 0
    while line.now < 2.0:
        timer = line.core.get_timer()
        event_at = line._events[0][0] if line._events else INFINITY
        when = min(INFINITY if timer is None else timer, event_at)
        stalled = stalled + 1 if when <= line.now else 0
        assert stalled < 50, f"the core asks for its timer at {when} again and again"
        line.now = max(line.now, when)
        if event_at <= line.now:
            line._heap.heappop(line._events)[2]()
        else:
            line.core.handle_timer(line.now)
        line._pump()
    assert [frame for frame in line.polls() if frame[0] == 1][:3] == [
        encode_rtu(1, read(48, 10))
    ] * 3  # polled on time at 0, 0.64 and 1.28 s


def test_a_reload_keeps_an_unchanged_blocks_schedule_even_while_it_fails() -> None:
    """Found by the polled line machine: a reload made an unchanged block due a period
    after its last good answer, so a failing block (no good answer) was polled again at
    once, and one whose poll was waiting twice in a row. Its schedule is kept; only a
    changed period moves it, counted from the last poll."""
    line = RegisterLine((block(count=10, every=1.0),))
    line.exceptions.add(1)
    line.run(0.5)
    config = LineConfig(name="t", device="/dev/null", baudrate=19200, polls=(block(count=10),))
    line.core.reconfigure(config, line.now)
    line._pump()
    line.run(0.99)
    assert len(line.polls()) == 1  # the one at 0 s; the next is due at 1 s
    faster = replace(config, polls=(block(count=10, every=0.2),))
    line.core.reconfigure(faster, line.now)
    line._pump()
    assert len(line.polls()) == 2  # due 0.2 s after the last poll: at once


def test_a_block_a_reload_adds_counts_the_writes_still_outstanding() -> None:
    """Found by the polled line machine: a write waited while a reload added a block over
    its register; the new block's first poll went before the write and was kept, and
    another master's read got the value from before the write, from memory."""
    line = RegisterLine((block(slave=2, count=10),))
    line.turnaround = 0.2
    line.run(0.5)
    line.submit(1, read(50), master="busy")  # holds the line 0.2 s
    line.submit(1, write(3, 777), master="writer")
    config = LineConfig(
        name="t", device="/dev/null", baudrate=19200, polls=(block(slave=2, count=10), block())
    )
    line.core.reconfigure(config, line.now)
    line._pump()
    line.run(0.95)  # the new block's poll went and was answered; the write is on the wire
    reader = line.submit(1, read(3), master="reader")
    line.run(2.0)
    pdu, outcome = line.answer_of(reader)
    assert pdu == bytes((3, 2)) + (777).to_bytes(2, "big"), (pdu.hex(), outcome)
