"""A lost answer reaches nobody, however late it comes: windows last until proof.

The line core on a simulated serial line of single-threaded slaves (``DeafWhileBusyLine``):
a slave that answers some reads up to 5 s late, later than anything learned, while masters
poll it flat out. Every answer carries the data of the request it answers, so an answer
delivered to another read is counted (``wrong``). Literal times, no event loop.
"""

from __future__ import annotations

import functools
import random

import pytest

from gateway.config import LineConfig, build_config
from gateway.core.line import LineCore, LineRequest
from gateway.core.line.late import proof_pdu
from gateway.core.line.records import answer_signature
from gateway.core.outcome import LineEvent, Outcome
from gateway.core.timing import character_time
from tests.helpers import read
from tests.line_harness import DeafWhileBusyLine

BAUD = 19200
CHAR = character_time(BAUD, 8, "N", 1)


def default_line(**settings: object) -> LineConfig:
    table = {"device": "/dev/null", "baudrate": BAUD, **settings}
    return build_config({"lines": {"a": table}}).lines[0]


def late_slaves(seed: int, share: float, longest: float, deaf: bool = True) -> DeafWhileBusyLine:
    """Slaves 1 and 2 answer in 5 ms, ``share`` of the time 0.45 s to ``longest`` late
    (``deaf``: hearing nothing meanwhile; else answering what they heard, in turn)."""
    draw = random.Random(seed)

    def turnaround(_slave: int, _pdu: bytes, _now: float) -> float:
        return draw.uniform(0.45, longest) if draw.random() < share else 0.005

    return DeafWhileBusyLine(LineCore(default_line(), -1.0), CHAR, turnaround, deaf)


def flat_out(line: DeafWhileBusyLine, masters: int, until: float) -> list[Outcome]:
    """``masters`` closed-loop masters, each reading 10 registers of slave 1 or 2 at an
    address of its own draw, the next as soon as the last is answered."""
    draw = random.Random(masters)
    outcomes: list[Outcome] = []

    def send(master: str) -> None:
        line.submit(master, draw.choice((1, 2)), read(draw.randrange(0, 9000), 10))

    def again(request: LineRequest, outcome: Outcome) -> None:
        outcomes.append(outcome)
        master = str(request.master)
        line.at(line.now + 0.001, lambda: send(master))  # its network round trip

    line.on_answer = again
    for index in range(masters):
        send(f"m{index}")
    line.run(until)
    return outcomes


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("deaf", [True, False])
def test_answers_late_by_up_to_five_seconds_reach_nobody(seed: int, deaf: bool) -> None:
    """5 % of reads answered 0.45-5 s late (the slave deaf meanwhile, or answering every
    request it heard in turn), two masters flat out on two slaves: not one answer is
    delivered to another read."""
    line = late_slaves(seed, 0.05, 5.0, deaf)
    outcomes = flat_out(line, 2, 120.0)
    assert line.wrong == 0
    assert Outcome.OK in outcomes


@pytest.mark.parametrize("seed", range(4))
def test_holding_is_not_refusing_most_reads_get_their_data(seed: int) -> None:
    """5 % of reads answered 0.45-1.3 s late: at least 90 % of the reads get their data,
    none another's."""
    line = late_slaves(seed, 0.05, 1.3)
    outcomes = flat_out(line, 2, 120.0)
    assert line.wrong == 0
    assert outcomes.count(Outcome.OK) >= 0.9 * len(outcomes), len(outcomes)


def test_a_window_that_closes_on_a_timer_delivers_late_answers_to_other_reads() -> None:
    """What the proof rule prevents: with a fixed late-answer window shorter than the
    slave's lateness, late answers are taken for other reads' answers."""
    line = late_slaves(0, 0.05, 5.0, deaf=False)
    line.core.reconfigure(default_line(late_answer_window=0.2), 0.0)
    flat_out(line, 2, 120.0)
    assert line.wrong > 0


def test_a_proof_read_lets_a_held_read_go_and_is_answered_to_nobody() -> None:
    """A slave known to answer loses one answer. The next read of the same length waits
    for proof: the line reads the slave itself (the same address, one register), and once
    that is answered the held read goes, with its own data."""
    answers: list[float | None] = [0.005, 0.005, 0.005, None]  # the fourth answer is lost

    def turnaround(_slave: int, _pdu: bytes, _now: float) -> float | None:
        return answers.pop(0) if answers else 0.005

    config = default_line(retries=0, dead_after=0)  # no isolation: the slave stays up
    line = DeafWhileBusyLine(LineCore(config, -1.0), CHAR, turnaround)
    for index in range(4):
        line.submit("a", 1, read(100, 10))
        line.run(1.5 * (index + 1))
    assert [outcome for _, _, outcome, _ in line.outcomes][-1] is Outcome.TARGET_FAILED
    line.submit("b", 1, read(200, 10))  # its answer would look like the lost one: held
    line.run(30.0)
    assert line.wrong == 0
    assert [(m, o) for m, _, o, _ in line.outcomes][-1] == ("b", Outcome.OK)
    assert read(100) in [frame[1:6] for frame in line.sent]  # the proof read
    assert [n.event for n in line.core.notes].count(LineEvent.PROOF_READ) == 1
    assert len(line.outcomes) == 5  # the proof read's answer went to nobody


def test_a_request_held_for_proof_of_a_down_slave_is_answered_at_once() -> None:
    """Holding is not waiting for ``max_queue_wait``: a slave that stopped answering goes
    down, and a request held by its window is answered 0x0B at once."""

    def turnaround(_slave: int, _pdu: bytes, now: float) -> float | None:
        return 0.005 if now < 1.0 else None

    line = DeafWhileBusyLine(LineCore(default_line(), -1.0), CHAR, turnaround)

    def poll(address: int) -> None:
        line.submit("m", 1, read(address, 10))

    for index in range(20):
        line.at(index * 0.1, functools.partial(poll, index))
    line.run(30.0)
    assert len(line.outcomes) == 20
    assert line.wrong == 0
    late = [(r.enqueued_at, o) for _, r, o, _ in line.outcomes if r.enqueued_at >= 1.0]
    assert Outcome.TARGET_FAILED in [outcome for _, outcome in late]
    down = line.core.slave_state(1).value
    assert down in ("suspect", "down")


def test_the_proof_read_is_one_whose_answer_looks_like_no_awaited_answer() -> None:
    awaited = {answer_signature(read(0, 10))}
    assert proof_pdu(awaited, read(40, 10), read(0, 10)) == read(40)
    assert proof_pdu(awaited, read(40, 3), read(0, 10)) == read(40, 3)  # known and distinct
    assert proof_pdu({answer_signature(read(0))}, None, read(7)) == read(7, 2)
    coils = bytes((1, 0, 5, 0, 4))  # 4 coils: one byte
    assert proof_pdu({answer_signature(coils)}, coils, None) == bytes((1, 0, 5, 0, 9))
    write = bytes((6, 0, 1, 0, 9))
    assert proof_pdu({answer_signature(write)}, None, write) is None
