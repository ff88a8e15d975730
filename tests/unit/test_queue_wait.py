"""``max_queue_wait`` with literal times: a request still unsent after it is answered 0x0B
without using the line, and the slave's health is not touched."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.config import LineConfig
from gateway.core.errors import ExceptionCode
from gateway.core.line import LineCore
from gateway.core.line.fair_queue import FairQueue
from gateway.core.line.records import LineRequest, LineStats, no_reply
from gateway.core.outcome import Outcome, SlaveState
from gateway.core.rtu import encode_rtu
from tests.helpers import read
from tests.line_harness import LineHarness

BAUD = 19200


def answer(slave: int) -> bytes:
    return encode_rtu(slave, bytes((3, 2, 0, 7)))


class Line(LineHarness):
    def __init__(self, **settings: Any) -> None:
        defaults: dict[str, Any] = {"baudrate": BAUD, "timeout": 3.0, "retries": 0}
        config = LineConfig(name="t", device="/dev/null", **{**defaults, **settings})
        super().__init__(LineCore(config, -1.0))


def test_a_request_unsent_after_max_queue_wait_is_answered_0x0b_without_the_wire() -> None:
    line = Line(max_queue_wait=2.0)
    first = line.submit(1, read(0), 0.0, master="a")  # goes at once; its slave is slow
    waiting = line.submit(2, read(1), 0.0, master="b")
    later = line.submit(2, read(2), 1.0, master="c")
    assert len(line.frames()) == 1
    assert line.core.get_timer() == pytest.approx(2.0)  # before the attempt's 3 s deadline
    line.timer()
    pdu, outcome = line.answer_of(waiting)
    assert outcome is Outcome.TARGET_FAILED
    assert pdu == bytes((0x83, ExceptionCode.GATEWAY_TARGET_FAILED))
    assert line.frames() == []  # not sent
    assert line.core.slave_state(2) is SlaveState.UP  # its slave's health is not touched
    assert line.core.health.slaves.get(2) is None or line.core.health.slaves[2].misses == 0
    assert line.unanswered() == [first, later]
    assert line.core.get_timer() == pytest.approx(3.0)  # ``later``'s patience ends too
    line.receive(answer(1), 2.5)  # the slow slave answers: ``later`` goes now
    assert line.answer_of(first)[1] is Outcome.OK
    assert line.timer() < 2.51  # after the frame gap
    assert len(line.frames()) == 1
    assert line.unanswered() == [later]


def test_a_request_sent_in_time_is_not_answered_by_its_old_deadline() -> None:
    line = Line(max_queue_wait=2.0)
    line.submit(1, read(0), 0.0, master="a")
    sent_in_time = line.submit(2, read(1), 0.0, master="b")
    line.receive(answer(1), 1.0)
    line.timer()  # the second request goes after the frame gap
    assert len(line.frames()) == 2
    assert (line.core.get_timer() or 0.0) > 3.0  # its patience no longer counts: the attempt's does
    line.core.handle_timer(2.0)
    assert line.unanswered() == [sent_in_time]  # nothing answered by it
    line.receive(answer(2), 2.5)
    assert line.answer_of(sent_in_time)[1] is Outcome.OK


def test_no_limit_with_zero() -> None:
    line = Line(max_queue_wait=0.0, timeout=10.0)
    line.submit(1, read(0), 0.0, master="a")
    waiting = line.submit(2, read(1), 0.0, master="b")
    line.frames()
    assert line.core.get_timer() == pytest.approx(10.0, abs=0.01)
    line.receive(answer(1), 9.0)
    line.timer()
    assert line.frames() == [encode_rtu(2, read(1))]
    assert line.unanswered() == [waiting]


def test_a_request_back_from_the_lane_keeps_its_patience() -> None:
    """A request that waited in the lane (its slave suspect) and goes back to the queue when
    the slave answers is answered 0x0B once ``max_queue_wait`` has passed since its master
    sent it, like any queued request, not held for ever behind what keeps the line busy."""
    queue = FairQueue(LineStats())
    older = LineRequest(2, read(1), "a", no_reply)
    older.enqueued_at = 0.0
    newer = LineRequest(3, read(2), "b", no_reply)
    newer.enqueued_at = 1.0
    queue.enqueue(queue.master("b"), newer, True, 1.0)
    queue.queue_at_front(older)  # back from the lane at 1.5
    assert queue.overdue(0.5) == [older]
    assert queue.overdue(1.5) == [newer]
    assert queue.queued == 0
