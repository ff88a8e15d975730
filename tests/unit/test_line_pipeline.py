"""Several requests in flight on one Modbus TCP line (``max_in_flight``), with literal times.

Each test drives ``PipelinedLineCore`` as the driver does and reads its decisions: the
ADUs it writes (each under its own transaction id), the answers it delivers, its timer.
"""

from __future__ import annotations

import struct
from typing import Any

import pytest

from gateway.cli import apply_overrides, build_parser
from gateway.config import CacheRule, ConfigError, LineConfig, build_config
from gateway.core.framing import is_mbap, mbap_framing
from gateway.core.line import LineCore, PipelinedLineCore, new_line_core
from gateway.core.mbap import encode_mbap
from gateway.core.outcome import LineEvent, Outcome, SlaveState
from tests.helpers import problems, read
from tests.line_harness import LineHarness

TIMEOUT = 0.5


def write(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def answer_to(pdu: bytes, value: int) -> bytes:
    """A normal answer to a read (every register ``value``) or a write (its echo)."""
    if pdu[0] in (3, 4):
        quantity = (pdu[3] << 8) | pdu[4]
        return bytes((pdu[0], 2 * quantity)) + struct.pack(f">{quantity}H", *[value] * quantity)
    return pdu


class Line(LineHarness):
    """A pipelined core, the ADUs it sent (by TID) and the answers it delivered."""

    def __init__(self, max_in_flight: int = 4, **settings: Any) -> None:
        defaults: dict[str, Any] = {"baudrate": 115200, "timeout": TIMEOUT, "retries": 1}
        self.config = LineConfig(
            name="t", device="tcp", kind="tcp", max_in_flight=max_in_flight,
            **{**defaults, **settings},
        )  # fmt: skip
        core = new_line_core(self.config, -1.0, None, mbap_framing(), max_in_flight)
        assert isinstance(core, PipelinedLineCore)
        super().__init__(core)
        self.wire: dict[int, tuple[int, bytes]] = {}  # TID -> (unit, PDU) of every ADU sent

    def sent(self) -> list[int]:
        """TIDs of the ADUs written since the last call."""
        tids = []
        for frame in self.frames():
            tid = (frame[0] << 8) | frame[1]
            self.wire[tid] = (frame[6], frame[7:])
            tids.append(tid)
        return tids

    def answer(self, tid: int, now: float, value: int = 0) -> None:
        unit, pdu = self.wire[tid]
        self.receive(encode_mbap(tid, unit, answer_to(pdu, value)), now)

    def timer(self, now: float | None = None) -> float:
        """Fire the timer at ``now``, whether or not the core asked for one."""
        assert now is not None
        self.core.handle_timer(now)
        self.flush()
        return now


def test_up_to_max_in_flight_go_at_once_and_answers_are_taken_in_any_order() -> None:
    line = Line(max_in_flight=3)
    reads = [line.submit(1, read(address), 0.0, master=f"m{address}") for address in range(5)]
    assert line.sent() == [1, 2, 3]  # the fourth and fifth wait for room
    assert line.core.in_flight == 3
    line.answer(3, 0.010, value=33)
    assert line.answer_of(reads[2]) == (answer_to(read(2), 33), Outcome.OK)
    assert line.sent() == [4]  # room again: the next one goes at once
    line.answer(1, 0.011, value=11)
    assert line.sent() == [5]
    line.answer(4, 0.012, value=44)
    line.answer(5, 0.013, value=55)
    line.answer(2, 0.014, value=22)
    for request, value in zip(reads, (11, 22, 33, 44, 55), strict=True):
        assert line.answer_of(request) == (answer_to(request.pdu, value), Outcome.OK)
    assert line.core.idle and line.core.get_timer() is None


def test_each_attempt_has_its_own_deadline_and_one_timing_out_spares_the_others() -> None:
    line = Line(max_in_flight=4)
    first = line.submit(1, read(0), 0.0)
    second = line.submit(2, read(1), 0.1)
    assert line.sent() == [1, 2]
    deadline = line.core.get_timer()
    assert deadline == 0.5  # the first one's, not a shared one
    line.answer(2, 0.2, value=7)
    assert line.answer_of(second) == (answer_to(read(1), 7), Outcome.OK)
    line.timer(deadline)  # the first times out: retried at once under a new TID
    assert [n.event for n in line.core.notes if n.event is LineEvent.TIMEOUT]
    assert line.sent() == [3]
    line.answer(1, deadline + 0.01, value=99)  # the lost attempt's late answer: its TID is stale
    assert line.discarded() == ["unexpected_tid"]
    assert line.unanswered() == [first]
    line.answer(3, deadline + 0.02, value=5)
    assert line.answer_of(first) == (answer_to(read(0), 5), Outcome.OK)


def test_a_stale_or_unknown_tid_is_never_delivered() -> None:
    line = Line()
    request = line.submit(1, read(0), 0.0)
    assert line.sent() == [1]
    line.core.receive(encode_mbap(77, 1, answer_to(read(0), 1)), 0.01)
    line.flush()
    assert line.discarded() == ["unexpected_tid"] and line.unanswered() == [request]
    line.answer(1, 0.02, value=2)
    assert line.answer_of(request) == (answer_to(read(0), 2), Outcome.OK)


def test_a_write_that_times_out_is_not_sent_again() -> None:
    line = Line()
    request = line.submit(1, write(0, 5), 0.0)
    assert line.sent() == [1]
    line.timer(1.0)
    assert line.sent() == []
    assert line.answer_of(request)[1] == Outcome.TARGET_FAILED


def test_port_loss_answers_every_outstanding_attempt_and_the_queue_once() -> None:
    line = Line(max_in_flight=3)
    requests = [line.submit(unit, read(unit), 0.0, master=f"m{unit}") for unit in (1, 2, 3, 4, 5)]
    assert line.sent() == [1, 2, 3]
    line.core.port_lost(0.05)
    line.flush()
    for request in requests:
        assert line.answer_of(request)[1] == Outcome.NO_ROUTE
    assert line.core.idle and line.core.get_timer() is None
    line.core.port_opened(0.1)  # a new connection: answers on the old one are not expected
    after = line.submit(1, read(9), 0.1)
    assert line.sent() == [4]
    line.core.receive(encode_mbap(2, 2, answer_to(read(2), 1)), 0.11)  # from the old stream
    line.answer(4, 0.12, value=3)
    assert line.answer_of(after) == (answer_to(read(9), 3), Outcome.OK)
    assert all(len(got) == 1 for got in line.answers.values())


def test_stop_lets_outstanding_attempts_finish_and_abandon_answers_them() -> None:
    line = Line()
    first, second = line.submit(1, read(0), 0.0), line.submit(2, read(0), 0.0)
    queued = [line.submit(3, read(n), 0.0, master="x") for n in range(3)]
    line.sent()
    line.core.stop(0.01)
    line.flush()
    assert all(line.answer_of(r)[1] == Outcome.NO_ROUTE for r in queued[2:])
    line.answer(1, 0.02)
    assert line.answer_of(first)[1] == Outcome.OK
    line.core.abandon(0.03)
    line.flush()
    assert line.answer_of(second)[1] == Outcome.NO_ROUTE
    assert line.core.idle and line.unanswered() == []


def test_a_write_waits_for_the_same_masters_earlier_requests_to_that_unit() -> None:
    line = Line()
    before = line.submit(1, read(0), 0.0)
    change = line.submit(1, write(0, 9), 0.0)
    after = line.submit(1, read(0), 0.0)
    elsewhere = line.submit(2, read(0), 0.0)  # another unit: not held
    other = line.submit(1, write(0, 8), 0.0, master="other")  # another master: not held
    assert [line.wire.get(t) for t in line.sent()] == [
        (1, read(0)), (2, read(0)), (1, write(0, 8)),
    ]  # fmt: skip
    line.answer(1, 0.01)
    assert line.answer_of(before)[1] == Outcome.OK
    assert line.sent() == [4]  # the write, alone: the read after it waits for its answer
    assert line.wire[4] == (1, write(0, 9))
    line.answer(4, 0.02)
    assert line.answer_of(change)[1] == Outcome.OK
    assert line.sent() == [5] and line.wire[5] == (1, read(0))
    for tid in (2, 3, 5):
        line.answer(tid, 0.03)
    assert {line.answer_of(r)[1] for r in (after, elsewhere, other)} == {Outcome.OK}


def test_reads_pass_reads_but_a_retried_read_still_holds_the_masters_write() -> None:
    line = Line(dead_after=0)  # isolation off: a timeout does not make the slave suspect
    reads = [line.submit(1, read(n), 0.0) for n in range(3)]
    change = line.submit(1, write(0, 1), 0.0)
    assert line.sent() == [1, 2, 3]
    line.answer(2, 0.01)
    line.answer(3, 0.01)
    assert line.sent() == []  # the first read is still outstanding
    line.timer(0.6)  # it times out: its retry goes, the write still waits
    assert line.sent() == [4] and line.wire[4] == (1, read(0))
    line.answer(4, 0.62)
    assert line.answer_of(reads[0])[1] == Outcome.OK
    assert line.sent() == [5] and line.wire[5] == (1, write(0, 1))
    line.answer(5, 0.63)
    assert line.answer_of(change)[1] == Outcome.OK


def test_identical_reads_still_share_one_transaction_while_they_wait() -> None:
    line = Line(max_in_flight=2)
    line.submit(1, read(7), 0.0, master="a")
    line.submit(1, read(8), 0.0, master="a")
    shared = [line.submit(2, read(0), 0.0, master=m) for m in ("b", "c", "d")]
    assert line.sent() == [1, 2]
    line.answer(1, 0.01)
    assert line.sent() == [3]
    line.answer(3, 0.02, value=4)
    assert [line.answer_of(r) for r in shared] == [(answer_to(read(0), 4), Outcome.OK)] * 3


def cache_unit_1() -> tuple[CacheRule, ...]:
    """The read-cache rules of a tcp line caching unit 1's registers 0-9 for 10 s."""
    return build_config(
        {"lines": {"t": {"kind": "tcp", "address": "h:502", "units": [1],
                         "cache": [{"unit": 1, "count": 10, "max_age": 10}]}}}
    ).line("t").cache  # fmt: skip


def test_a_read_overtaken_by_a_write_is_not_cached() -> None:
    line = Line(cache=cache_unit_1())
    line.submit(1, read(0), 0.0, master="a")
    line.submit(1, write(0, 3), 0.0, master="b")
    assert line.sent() == [1, 2]
    line.answer(2, 0.01)  # the write is done
    line.answer(1, 0.02, value=0)  # the read went before it: its value may be the old one
    again = line.submit(1, read(0), 0.03, master="c")
    assert line.sent() == [3]  # not served from the cache
    line.answer(3, 0.04, value=3)
    assert line.answer_of(again) == (answer_to(read(0), 3), Outcome.OK)
    cached = line.submit(1, read(0), 0.05, master="d")
    assert line.answer_of(cached)[1] == Outcome.CACHED  # a read with no write after it is


@pytest.mark.parametrize("write_answered_first", [False, True])
def test_a_read_sent_while_a_write_is_outstanding_is_not_cached(
    write_answered_first: bool,
) -> None:
    """The write went first but is still unanswered when the read goes: the device may run
    the read before it, so the read's value may be the one before the write, whichever of
    the two answers comes first, and must not answer later reads."""
    line = Line(cache=cache_unit_1())
    line.submit(1, write(0, 3), 0.0, master="a")
    line.submit(1, read(0), 0.0, master="b")
    assert line.sent() == [1, 2]
    if write_answered_first:
        line.answer(1, 0.01)
        line.answer(2, 0.02, value=0)
    else:
        line.answer(2, 0.01, value=0)
        line.answer(1, 0.02)
    line.submit(1, read(0), 0.03, master="a")
    assert line.sent() == [3]  # not served from the cache


def test_a_polite_master_is_next_when_a_slot_of_a_deep_pipeline_frees() -> None:
    line = Line(max_in_flight=2)
    for n in range(4):  # one transaction each to learn how long they take
        line.submit(1, read(n), 0.0, master="greedy")
        (tid,) = line.sent()
        line.answer(tid, 0.01 * (n + 1))
    for n in range(10):
        line.submit(1, read(n), 0.1, master="greedy")
    polite = line.submit(1, read(100), 0.1, master="polite")
    first, _second = line.sent()  # both slots to the master who asked first
    line.answer(first, 0.11)
    (third,) = line.sent()
    assert line.wire[third] == (1, read(100))  # the polite master's, not greedy's third
    line.answer(third, 0.12)
    assert line.answer_of(polite)[1] == Outcome.OK


def test_a_broadcast_waits_for_the_outstanding_attempts_and_goes_alone() -> None:
    line = Line(broadcast_turnaround=0.1)
    line.submit(1, read(0), 0.0, master="a")
    line.submit(2, read(0), 0.0, master="a")
    broadcast = line.submit(0, write(0, 1), 0.0, master="b")
    later = line.submit(3, read(0), 0.0, master="c")
    assert line.sent() == [1, 2]  # nothing more while the broadcast waits
    line.answer(1, 0.01)
    assert line.sent() == []
    line.answer(2, 0.02)
    assert line.sent() == [3] and line.wire[3][0] == 0
    assert line.answer_of(broadcast)[1] == Outcome.BROADCAST
    assert line.core.get_timer() == pytest.approx(0.12)  # the turnaround
    line.timer(0.125)
    assert line.sent() == [4]
    line.answer(4, 0.13)
    assert line.answer_of(later)[1] == Outcome.OK


def test_a_silent_slave_turns_suspect_while_another_units_answers_flow() -> None:
    line = Line(retries=0)
    silent = [line.submit(9, read(n), 0.0, master=f"s{n}") for n in range(2)]
    healthy = line.submit(1, read(0), 0.0)
    assert line.sent() == [1, 2, 3]
    line.answer(3, 0.01)
    assert line.answer_of(healthy)[1] == Outcome.OK
    line.timer(0.6)
    assert line.core.slave_state(9) is SlaveState.SUSPECT
    assert [line.answer_of(r)[1] for r in silent] == [Outcome.TARGET_FAILED] * 2
    line.core.receive(encode_mbap(1, 9, answer_to(read(0), 0)), 0.7)  # late: it is alive
    assert line.core.slave_state(9) is SlaveState.UP


def test_a_header_out_of_step_is_noted_once_and_the_rest_ignored() -> None:
    line = Line()
    request = line.submit(1, read(0), 0.0)
    line.sent()
    line.core.receive(bytes.fromhex("0001 0007 0005 01 030200"), 0.01)
    line.core.receive(encode_mbap(1, 1, answer_to(read(0), 1)), 0.02)
    line.flush()
    assert line.discarded() == ["bad_header", "late"]
    assert line.unanswered() == [request]  # the driver reconnects: port loss answers it
    line.core.port_lost(0.03)
    line.flush()
    assert line.answer_of(request)[1] == Outcome.NO_ROUTE


def test_one_in_flight_is_the_serial_core_itself() -> None:
    config = LineConfig(name="t", device="tcp", kind="tcp")
    assert type(new_line_core(config, 0.0, None, mbap_framing(), 1)) is LineCore
    with pytest.raises(ValueError, match="transaction ids"):
        PipelinedLineCore(config, 0.0, None, max_in_flight=2)  # RTU framing
    assert is_mbap("tcp") and is_mbap("tls")
    assert not is_mbap("rtu") and not is_mbap("ascii") and not is_mbap("rtu-over-tcp")


def test_max_in_flight_in_the_configuration() -> None:
    tcp = {"kind": "tcp", "address": "10.0.0.9:502", "units": [1]}
    assert build_config({"lines": {"n": tcp}}).line("n").max_in_flight == 1
    assert build_config({"lines": {"n": {**tcp, "max_in_flight": 4}}}).line("n").max_in_flight == 4
    assert problems({"lines": {"n": {**tcp, "max_in_flight": 0}}}) == [
        "lines.n.max_in_flight: 0 outside 1..64"
    ]
    assert problems({"lines": {"n": {**tcp, "max_in_flight": 65}}}) == [
        "lines.n.max_in_flight: 65 outside 1..64"
    ]
    for table in (
        {"device": "/dev/ttyUSB0", "units": [1]},
        {"kind": "rtu-over-tcp", "address": "10.0.0.5:4001", "units": [1]},
    ):
        (problem,) = problems({"lines": {"n": {**table, "max_in_flight": 2}}})
        assert problem.startswith("lines.n.max_in_flight: only a Modbus TCP line")
        assert "remove the key" in problem


def test_a_tls_line_takes_max_in_flight_too() -> None:
    table = {"kind": "tls", "address": "plc:802", "units": [1], "cert": "c.pem", "key": "k.pem",
             "ca": "ca.pem", "max_in_flight": 3}  # fmt: skip
    assert build_config({"lines": {"n": table}}).line("n").max_in_flight == 3


def test_the_max_in_flight_flag() -> None:
    args = build_parser().parse_args(["--modbus-tcp", "10.0.0.9:502", "--max-in-flight", "4"])
    assert build_config(apply_overrides({}, args)).line("default").max_in_flight == 4
    raw = {"lines": {"a": {"device": "/dev/ttyS0", "units": [1]},
                     "b": {"kind": "tcp", "address": "h:502", "units": [2]}}}  # fmt: skip
    config = build_config(apply_overrides(raw, build_parser().parse_args(["--max-in-flight", "2"])))
    assert (config.line("a").max_in_flight, config.line("b").max_in_flight) == (1, 2)
    with pytest.raises(ConfigError, match="only a Modbus TCP or TLS line takes it"):
        apply_overrides({}, build_parser().parse_args(["--serial", "x", "--max-in-flight", "2"]))
    args = build_parser().parse_args(["--modbus-tcp", "h:502", "--max-in-flight", "99"])
    with pytest.raises(ConfigError) as caught:
        build_config(apply_overrides({}, args))
    assert caught.value.problems == ["lines.default.max_in_flight: 99 outside 1..64"]


def test_a_read_that_joined_another_masters_holds_its_masters_write_back() -> None:
    line = Line(max_in_flight=2)
    line.submit(3, read(9), 0.0, master="b")  # b has used the line: c comes first from now on
    line.answer(line.sent()[0], 0.1)
    line.submit(1, read(0), 0.2, master="a")
    line.submit(1, read(1), 0.2, master="a")
    assert line.sent() == [2, 3]  # both slots taken
    line.submit(2, read(5), 0.2, master="b")
    joined = line.submit(2, read(5), 0.2, master="c")  # shares b's transaction
    change = line.submit(2, write(5, 1), 0.2, master="c")
    line.answer(2, 0.3)
    assert [line.wire[tid] for tid in line.sent()] == [(2, read(5))]  # not c's write
    line.answer(4, 0.4, value=6)
    assert line.answer_of(joined) == (answer_to(read(5), 6), Outcome.OK)
    assert [line.wire[tid] for tid in line.sent()] == [(2, write(5, 1))]
    line.answer(5, 0.5)
    assert line.answer_of(change)[1] == Outcome.OK


def test_slots_freed_together_are_shared_in_fair_order_not_taken_by_one_master() -> None:
    line = Line(max_in_flight=4)
    line.submit(1, read(0), 0.0, master="greedy")  # greedy has used 10 ms of the line
    line.answer(line.sent()[0], 0.010)
    line.submit(1, read(1), 0.020, master="polite")  # polite 12 ms: slightly more
    line.answer(line.sent()[0], 0.032)
    for n in range(4):
        line.submit(2, read(n), 0.040, master="x")
    x_tids = line.sent()
    assert len(x_tids) == 4  # every slot taken
    for n in range(6):
        line.submit(1, read(10 + n), 0.041, master="greedy")
    polite = line.submit(1, read(100), 0.041, master="polite")
    answers = b"".join(
        encode_mbap(tid, 2, answer_to(line.wire[tid][1], 0)) for tid in x_tids
    )  # all four answers in one read: four slots free at once
    line.core.receive(answers, 0.042)
    line.flush()
    sent = [line.wire[tid] for tid in line.sent()]
    assert len(sent) == 4
    # Each send charges its master the recent average: greedy's small head start is used
    # up after a send or two, and polite gets a slot among these four.
    assert (1, read(100)) in sent
    for tid in list(line.wire)[-4:]:
        line.answer(tid, 0.05)
    assert line.answer_of(polite)[1] == Outcome.OK


def test_changing_max_in_flight_on_reload_reconnects_the_line() -> None:
    from dataclasses import replace

    from gateway.app import _port_changed

    line = LineConfig(name="t", device="h:502", kind="tcp")
    assert _port_changed(line, replace(line, max_in_flight=4))
    assert not _port_changed(line, replace(line, timeout=2.0))


def test_a_masters_read_does_not_join_another_masters_while_its_own_write_is_outstanding() -> None:
    """b's read may go while a's write is still outstanding (it holds only a's requests):
    a's read after its write must not share it, or its answer could predate the write."""
    line = Line(max_in_flight=2)
    line.submit(2, read(60), 0.0, master="x")
    line.submit(1, write(0, 3), 0.0, master="a")
    assert line.sent() == [1, 2]
    shared = line.submit(1, read(0), 0.001, master="b")  # waits for a free slot
    mine = line.submit(1, read(0), 0.002, master="a")
    assert shared.followers == []
    line.answer(1, 0.01)
    assert line.sent() == [3]  # b's read, while a's write is outstanding
    line.answer(2, 0.02)  # the write is done: now a's read goes
    assert line.sent() == [4]
    assert line.wire[4] == (1, read(0))
    line.answer(4, 0.03, value=3)
    assert line.answer_of(mine) == (answer_to(read(0), 3), Outcome.OK)
