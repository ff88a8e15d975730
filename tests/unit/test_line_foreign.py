"""A second master on the line: its frames are noticed, and its answers never reach ours.

Literal times, the core alone (``LineHarness``): a foreign master's frames are bytes the
core receives without having sent anything that asks for them.
"""

from __future__ import annotations

import struct
from typing import Any

import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from gateway.config import LineConfig
from gateway.core.ascii import encode_ascii
from gateway.core.crc import crc16
from gateway.core.framing import ASCII, RTU, Framing, mbap_framing
from gateway.core.line import LineCore, LineRequest
from gateway.core.line.foreign import OWN_ECHO_FOR_S, SHARED_FOR_S
from gateway.core.line.response_timing import EVIDENCE, MARGIN, answer_pdu_length
from gateway.core.outcome import LineEvent, Outcome
from gateway.core.rtu import encode_rtu
from gateway.core.timing import character_time
from tests.helpers import read
from tests.line_harness import LineHarness

BAUD = 19200
CHAR = character_time(BAUD, 8, "N", 1)


def write_registers(address: int, values: list[int]) -> bytes:
    count = len(values)
    return struct.pack(f">BHHB{count}H", 16, address, count, 2 * count, *values)


def registers_answer(slave: int, request: bytes, first: int) -> bytes:
    quantity = (request[3] << 8) | request[4]
    values = [(first + index) & 0xFFFF for index in range(quantity)]
    pdu = bytes((request[0], 2 * quantity)) + struct.pack(f">{quantity}H", *values)
    return encode_rtu(slave, pdu)


class Line(LineHarness):
    """A serial line's core, with literal times."""

    def __init__(self, framing: Framing = RTU, **settings: Any) -> None:
        defaults: dict[str, Any] = {"baudrate": BAUD, "timeout": 0.5, "retries": 1}
        kind = "ascii" if framing is ASCII else "rtu"
        self.config = LineConfig(
            name="f", device="/dev/null", kind=kind, **{**defaults, **settings}
        )
        super().__init__(LineCore(self.config, -1.0, framing=framing))

    def advance(self, now: float) -> None:
        """Fire every timer due by ``now``."""
        while (deadline := self.core.get_timer()) is not None and deadline <= now:
            self.timer()

    def foreign_notes(self) -> int:
        return len(self.notes(LineEvent.FOREIGN_MASTER))


# --------------------------------------------------------------------------- detection


def test_a_foreign_request_on_an_idle_line_is_counted_and_the_line_is_shared() -> None:
    line = Line()
    assert not line.core.shared and line.core.last_master_frame_at is None
    line.receive(encode_rtu(7, read(0, 2)), 1.0)
    assert line.foreign_notes() == 1
    assert line.core.foreign_frames == 1
    assert line.core.shared
    assert line.core.last_master_frame_at == 1.0
    assert line.core.last_frame_at == 1.0
    assert line.core.get_timer() == pytest.approx(1.0 + SHARED_FOR_S)
    line.advance(1.0 + SHARED_FOR_S - 0.001)
    assert line.core.shared
    line.advance(1.0 + SHARED_FOR_S)
    assert not line.core.shared
    assert len(line.notes(LineEvent.LINE_NOT_SHARED)) == 1
    assert line.core.get_timer() is None
    assert line.core.last_master_frame_at == 1.0  # the hook keeps the last one


def test_a_foreign_request_split_across_reads_and_behind_noise_is_found_once() -> None:
    line = Line()
    frame = encode_rtu(7, read(0, 2))
    line.receive(b"\x00" + frame[:3], 1.0)
    line.receive(frame[3:], 1.0 + 5 * CHAR)
    assert line.foreign_notes() == 1
    assert line.core.last_master_frame_at == 1.0 + 5 * CHAR


def test_a_slave_answer_alone_is_a_frame_not_a_master() -> None:
    line = Line()
    line.receive(registers_answer(7, read(0, 2), 1), 1.0)
    assert line.foreign_notes() == 0
    assert not line.core.shared
    assert line.core.last_frame_at == 1.0
    assert line.core.last_master_frame_at is None


def test_our_own_echo_is_not_a_foreign_master() -> None:
    line = Line(echo=True)
    request = line.submit(1, read(100, 2), 0.0)
    sent = line.frames()[0]
    line.receive(sent, len(sent) * CHAR)  # the adapter hears itself
    line.receive(registers_answer(1, read(100, 2), 5), 0.02)
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.foreign_notes() == 0 and not line.core.shared


@pytest.mark.parametrize("pdu", [bytes.fromhex("0600070002"), bytes.fromhex("050010FF00")])
def test_the_echo_of_our_own_fc5_or_fc6_request_is_our_answer(pdu: bytes) -> None:
    line = Line()
    request = line.submit(1, pdu, 0.0)
    line.receive(line.frames()[0], 0.02)  # the slave's answer is the request itself
    assert line.answer_of(request) == (pdu, Outcome.OK)
    assert line.foreign_notes() == 0


def test_a_late_fc6_answer_of_our_lost_attempt_is_not_a_foreign_master() -> None:
    line = Line(retries=0, late_answer_window=1.0)  # the window closes before the reload
    pdu = bytes.fromhex("0600070002")
    request = line.submit(1, pdu, 0.0)
    frame = line.frames()[0]
    failed_at = line.timer()  # no answer in time: 0x0B, the late-answer window opens
    assert line.answer_of(request)[1] == Outcome.TARGET_FAILED
    assert line.core.late.windows
    line.receive(frame, failed_at + 0.1)
    assert line.foreign_notes() == 0


@pytest.mark.parametrize("pdu", [bytes.fromhex("0600070002"), bytes.fromhex("050010FF00")])
def test_a_very_late_echo_of_our_write_is_not_a_foreign_master(pdu: bytes) -> None:
    """A slave that answers a write after its late-answer window closed: the copy of our
    frame is its answer (a redundancy pair would otherwise step down for it), for
    ``OWN_ECHO_FOR_S``; after that the same frame is another master's."""
    line = Line(retries=0, late_answer_window=0.5)
    request = line.submit(1, pdu, 0.0)
    frame = line.frames()[0]
    line.timer()
    assert line.answer_of(request)[1] == Outcome.TARGET_FAILED
    line.submit(2, read(0, 2), 1.5)  # traffic: the late-answer window is closed on the way
    line.advance(3.0)
    assert 1 not in line.core.late.windows  # the late-answer guard knows the write no more
    line.receive(frame, OWN_ECHO_FOR_S - 0.1)
    assert line.foreign_notes() == 0 and not line.core.shared
    line.receive(frame, OWN_ECHO_FOR_S + 1.0)
    assert line.foreign_notes() == 1 and line.core.shared


def test_a_foreign_request_heard_while_our_attempt_waits_is_counted() -> None:
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    line.frames()
    foreign = encode_rtu(2, read(0, 2))
    line.receive(foreign[:4], 0.010)  # taken by our attempt's decoder, no verdict yet
    line.receive(foreign[4:], 0.012)  # now refused: heard as another master's
    assert line.foreign_notes() == 1
    line.receive(registers_answer(1, read(100, 2), 9), 0.03)
    assert line.answer_of(request)[1] == Outcome.OK


def test_an_ascii_line_notices_a_foreign_request() -> None:
    line = Line(ASCII)
    line.receive(b"noise" + encode_ascii(7, read(0, 2))[:9], 1.0)
    line.receive(encode_ascii(7, read(0, 2))[9:], 1.01)
    assert line.foreign_notes() == 1 and line.core.shared


# --------------------------------------------------------------------------- no wrong answers


def test_a_look_alike_request_waits_for_the_foreign_requests_answer() -> None:
    line = Line()
    line.receive(encode_rtu(1, read(0, 2)), 0.0)  # another master reads 2 registers of slave 1
    request = line.submit(1, read(100, 2), 0.01)  # so do we, other registers: same answer shape
    assert line.frames() == []  # its answer could not be told from the other master's
    assert line.core.get_timer() == pytest.approx(3.0)  # at most until the foreign one expires
    other = line.submit(2, read(100, 2), 0.01)  # another slave is served meanwhile
    assert line.frames() == [encode_rtu(2, read(100, 2))]
    line.receive(registers_answer(2, read(100, 2), 1), 0.02)
    assert line.answer_of(other)[1] == Outcome.OK
    line.receive(registers_answer(1, read(0, 2), 500), 0.03)  # the foreign read's answer
    line.advance(0.04)
    assert line.frames() == [encode_rtu(1, read(100, 2))]
    line.receive(registers_answer(1, read(100, 2), 7), 0.06)
    assert line.answer_of(request) == (registers_answer(1, read(100, 2), 7)[1:-2], Outcome.OK)


def test_a_look_alike_goes_once_the_unanswered_foreign_request_expires() -> None:
    line = Line(learn_timeouts=True, max_timeout=1.0)
    line.receive(encode_rtu(1, read(0, 2)), 0.0)  # never answered
    request = line.submit(1, read(100, 2), 0.01)
    line.advance(0.999)
    assert line.frames() == []
    line.advance(1.0)
    assert line.frames() == [encode_rtu(1, read(100, 2))]
    line.receive(registers_answer(1, read(100, 2), 7), 1.02)
    assert line.answer_of(request)[1] == Outcome.OK


def ambiguous(line: Line, ours: bytes, theirs: bytes, answer: bytes) -> LineRequest:
    """Our request goes; another master's look-alike is heard while ours waits; an answer."""
    request = line.submit(1, ours, 0.0)
    assert line.frames() == [encode_rtu(1, ours)]
    line.receive(encode_rtu(1, theirs), 0.005)  # not a damaged answer: ours is still awaited
    assert line.notes(LineEvent.CRC_ERROR) == [] and request.answered is False
    line.receive(answer, 0.02)  # whose? it cannot be told
    return request


def test_an_answer_a_foreign_read_may_own_is_retried_not_delivered() -> None:
    line = Line()
    request = ambiguous(line, read(100, 2), read(0, 2), registers_answer(1, read(0, 2), 500))
    assert line.answers == {}
    assert len(line.notes(LineEvent.SHARED_ANSWER)) == 1
    line.advance(0.03)
    assert line.frames() == []  # the retry waits: the other answer is still to come
    line.receive(registers_answer(1, read(100, 2), 9), 0.04)  # both answers have come now
    line.advance(0.05)
    assert line.frames() == [encode_rtu(1, read(100, 2))]  # the retry
    line.receive(registers_answer(1, read(100, 2), 7), 0.07)
    assert line.answer_of(request) == (registers_answer(1, read(100, 2), 7)[1:-2], Outcome.OK)


def test_without_retries_the_ambiguous_answer_is_0x0b() -> None:
    line = Line(retries=0)
    request = ambiguous(line, read(100, 2), read(0, 2), registers_answer(1, read(100, 2), 500))
    assert line.answer_of(request) == (bytes((0x83, 0x0B)), Outcome.TARGET_FAILED)


def test_an_ambiguous_answer_to_a_write_is_0x0b_never_sent_again() -> None:
    line = Line(retries=3)
    ours, theirs = write_registers(10, [3, 4]), write_registers(10, [1, 2])
    request = ambiguous(line, ours, theirs, encode_rtu(1, ours[:5]))  # the same echo
    assert line.answer_of(request) == (bytes((0x90, 0x0B)), Outcome.TARGET_FAILED)
    line.advance(5.0)
    assert line.frames() == []


def test_an_exception_may_be_the_foreign_requests_too() -> None:
    line = Line(retries=0)
    request = ambiguous(line, read(100, 2), read(0, 5), encode_rtu(1, bytes((0x83, 0x02))))
    assert line.answer_of(request)[1] == Outcome.TARGET_FAILED


def test_an_answer_of_another_length_is_ours_and_delivered() -> None:
    line = Line()
    line.receive(encode_rtu(1, read(0, 3)), 0.0)  # the foreign read's answer has 6 bytes
    request = line.submit(1, read(100, 2), 0.01)
    line.receive(registers_answer(1, read(100, 2), 7), 0.03)
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.notes(LineEvent.SHARED_ANSWER) == []


def test_once_the_foreign_request_is_answered_our_answer_is_delivered() -> None:
    line = Line()
    line.receive(encode_rtu(1, read(0, 2)), 0.0)
    line.receive(registers_answer(1, read(0, 2), 500), 0.02)  # its answer, on an idle line
    request = line.submit(1, read(100, 2), 0.05)
    line.receive(registers_answer(1, read(100, 2), 7), 0.07)
    assert line.answer_of(request)[1] == Outcome.OK


def test_a_foreign_request_expires_after_the_longest_timeout() -> None:
    line = Line(learn_timeouts=True, max_timeout=1.0)
    line.receive(encode_rtu(1, read(0, 2)), 0.0)  # never answered
    request = line.submit(1, read(100, 2), 1.0)
    line.receive(registers_answer(1, read(100, 2), 7), 1.02)
    assert line.answer_of(request)[1] == Outcome.OK


def test_an_identical_foreign_write_shares_our_answer() -> None:
    line = Line()
    pdu = bytes.fromhex("0600070002")
    line.receive(encode_rtu(1, pdu), 0.0)
    request = line.submit(1, pdu, 0.01)
    line.receive(encode_rtu(1, pdu), 0.03)  # the same write's echo: ours either way
    assert line.answer_of(request) == (pdu, Outcome.OK)


# --------------------------------------------------------------------------- what a pair reads


def test_a_listening_line_learns_a_slaves_timing_from_the_answers_it_hears() -> None:
    line = Line(learn_timeouts=True)
    line.core.set_listening(True)
    assert line.core.timing.learned(5, 3) is None
    request = read(0, 10)
    answer = registers_answer(5, request, 0)
    turnaround = 0.2
    for index in range(EVIDENCE):  # the bound falls below initial_timeout on evidence only
        at = 1.0 + index
        line.receive(encode_rtu(5, request), at)
        line.receive(answer, at + turnaround + len(answer) * CHAR)
    assert line.core.timing.learned(5, 3) == pytest.approx(turnaround * MARGIN)
    assert line.core.heard_master_frames == EVIDENCE
    assert line.core.foreign_frames == 0
    assert line.foreign_notes() == 0 and not line.core.shared
    assert line.core.last_master_frame_at == at
    assert line.core.last_frame_at == pytest.approx(at + turnaround + len(answer) * CHAR)


def test_a_line_that_is_not_listening_learns_too() -> None:
    line = Line(learn_timeouts=True)
    line.receive(encode_rtu(5, read(0, 2)), 1.0)
    line.receive(registers_answer(5, read(0, 2), 0), 1.3)
    assert line.core.timing.learned(5, 3) is not None
    assert line.core.shared and line.core.heard_master_frames == 0


def test_listening_ends_and_foreign_frames_count_again() -> None:
    line = Line()
    line.core.set_listening(True)
    line.receive(encode_rtu(5, read(0, 2)), 1.0)
    line.core.set_listening(False)
    line.receive(encode_rtu(5, read(0, 2)), 2.0)
    assert (line.core.heard_master_frames, line.core.foreign_frames) == (1, 1)
    assert line.foreign_notes() == 1


# --------------------------------------------------------------------------- the invariant


@settings(max_examples=300, deadline=None)
@given(
    order=st.permutations(["submit", "foreign", "answer"]),
    gaps=st.lists(st.sampled_from([0.0, 0.001, 0.004, 0.02, 0.3]), min_size=3, max_size=3),
    foreign_quantity=st.sampled_from([2, 3]),
    answer_for_ours=st.booleans(),
    split=st.integers(0, 8),
)
def test_our_request_never_takes_an_answer_a_pending_foreign_request_may_own(
    order: list[str], gaps: list[float], foreign_quantity: int, answer_for_ours: bool, split: int
) -> None:
    """Our read, another master's read of the same slave and function, one answer, in any
    order: our read is answered OK only when no foreign read with its answer's signature
    was heard before that answer."""
    line = Line(retries=2)
    ours, foreign = read(100, 2), read(0, foreign_quantity)
    answer = registers_answer(1, ours if answer_for_ours else foreign, 7)
    now = 0.0
    request: LineRequest | None = None
    pending_alike = False  # a foreign read with our signature heard, its answer not yet
    for step, gap in zip(order, gaps, strict=True):
        now += gap
        line.advance(now)
        if step == "submit":
            request = line.submit(1, ours, now)
        elif step == "foreign":
            frame = encode_rtu(1, foreign)
            line.receive(frame[:split], now)
            line.receive(frame[split:], now + 0.0005)
            now += 0.0005
            pending_alike = foreign_quantity == 2
        else:
            alike = pending_alike
            line.receive(answer, now)
            if request is not None and request.answered:
                assert not alike, "an answer a foreign read may own reached ours"
            pending_alike = False
    line.advance(now + 60.0)
    assert request is not None
    pdu, outcome = line.answer_of(request)
    if outcome == Outcome.OK:
        assert pdu == answer[1:-2]


def test_a_reload_keeps_what_the_line_heard() -> None:
    line = Line()
    line.core.set_listening(True)
    line.receive(encode_rtu(1, read(0, 2)), 1.0)  # the peer's read, awaiting its answer
    line.core.set_listening(False)
    line.receive(encode_rtu(2, read(0, 2)), 1.5)
    handover = line.core.handover()
    fresh = Line()
    fresh.core.take_over(handover, 2.0)
    core = fresh.core
    assert core.shared and core.listening is False
    assert (core.heard_master_frames, core.foreign_frames) == (1, 1)
    assert core.last_master_frame_at == 1.5
    request = fresh.submit(1, read(100, 2), 2.0)
    fresh.receive(registers_answer(1, read(0, 2), 500), 2.02)  # still may be the peer's
    assert request.answered is False
    assert fresh.core.get_timer() is not None


def test_a_reload_keeps_the_writes_whose_very_late_echo_is_ours() -> None:
    line = Line(retries=0, late_answer_window=1.0)  # the window closes before the reload
    pdu = bytes.fromhex("0600070002")
    line.submit(1, pdu, 0.0)
    frame = line.frames()[0]
    line.timer()  # no answer in time: 0x0B
    fresh = Line()
    fresh.core.take_over(line.core.handover(), 2.0)
    assert not fresh.core.late.windows  # closed before the reload: not handed on
    fresh.receive(frame, 5.0)  # the slave's answer to the old line's write, 5 s late
    assert fresh.foreign_notes() == 0 and not fresh.core.shared


def test_last_frame_at_counts_the_answers_to_our_own_requests_too() -> None:
    line = Line()
    line.submit(1, read(100, 2), 0.0)
    line.receive(registers_answer(1, read(100, 2), 7), 0.03)
    assert line.core.last_frame_at == 0.03
    assert line.core.last_master_frame_at is None
    line.receive(registers_answer(9, read(0, 2), 7), 0.5)  # another master's slave, heard
    assert line.core.last_frame_at == 0.5


def test_a_held_retry_goes_once_the_foreign_request_expires() -> None:
    line = Line(learn_timeouts=True, max_timeout=1.0)
    request = ambiguous(line, read(100, 2), read(0, 2), registers_answer(1, read(0, 2), 500))
    line.advance(1.004)
    assert line.frames() == []
    line.advance(1.006)  # the foreign read, heard at 0.005, is given up
    assert line.frames() == [encode_rtu(1, read(100, 2))]
    line.receive(registers_answer(1, read(100, 2), 7), 1.03)
    assert line.answer_of(request)[1] == Outcome.OK


def test_frames_in_one_read_during_our_attempt_are_taken_in_order() -> None:
    """The other master's request, then two answers, read at once while ours waits: the
    first answer is refused (whose?), the second settles both, the retry is answered. The
    request-shaped frame comes from the slave our attempt asks: it is awaited as a foreign
    request (the protection holds) but not counted as another master (it may be that
    slave's malformed answer)."""
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    line.frames()
    theirs, ours = registers_answer(1, read(0, 2), 500), registers_answer(1, read(100, 2), 7)
    line.receive(encode_rtu(1, read(0, 2)) + theirs + ours, 0.02)
    assert line.foreign_notes() == 0 and len(line.notes(LineEvent.SHARED_ANSWER)) == 1
    assert not line.core.shared
    line.advance(0.03)
    assert line.frames() == [encode_rtu(1, read(100, 2))]
    line.receive(ours, 0.05)
    assert line.answer_of(request) == (ours[1:-2], Outcome.OK)


def test_a_foreign_request_right_behind_our_answer_is_heard() -> None:
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    line.frames()
    line.receive(registers_answer(1, read(100, 2), 7) + encode_rtu(1, read(0, 2)), 0.02)
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.foreign_notes() == 1


def test_an_expired_foreign_request_never_puts_the_timer_in_the_past() -> None:
    line = Line(learn_timeouts=True, max_timeout=1.0)
    line.receive(encode_rtu(9, read(0, 2)), 0.0)  # a slave this gateway never asks: until 1.0
    line.receive(b"\x00", 2.0)  # the line is busy a moment
    line.submit(1, read(100, 2), 2.0)  # so this waits for the gap
    line.timer(2.0)  # a driver late for its timer
    assert line.core.foreign.pending == {}
    deadline = line.core.get_timer()
    assert deadline is not None and deadline > 2.0


def answers(request: bytes, frame: bytes) -> bool:
    """True when RTU ``frame`` has the shape of the answer to RTU ``request``."""
    return (
        frame[0] == request[0]
        and frame[1] == request[1]
        and answer_pdu_length(request[1:-2]) == len(frame) - 3
        and frame[2] == len(frame) - 5
    )


@settings(max_examples=200, deadline=None)
@example(requests=[(4, 1, 0, 1), (4, 1, 672, 13)], cuts=[])  # a CRC that passes both ways
@example(requests=[(3, 1, 0, 1), (3, 1, 16383, 16)], cuts=[])  # as long as that answer
@given(
    requests=st.lists(
        st.tuples(
            st.integers(1, 4),
            st.sampled_from([1, 3, 4]),
            st.integers(0, 0xFFFF),
            st.integers(1, 40),
        ),
        min_size=1,
        max_size=6,
    ),
    cuts=st.lists(st.integers(0, 200), max_size=6),
)
def test_back_to_back_foreign_requests_split_anyhow_are_each_heard_once(
    requests: list[tuple[int, int, int, int]], cuts: list[int]
) -> None:
    """Requests of other masters read in pieces cut anywhere: each one heard, once. A
    request that is also, byte for byte, the answer to an earlier one to its slave (read
    17 coils of slave 1, then ``01 01 03 00 00 01``: 3 bytes of coils, or a read at
    0x0300) is taken for the answer, as the bus's turn says: left out here."""
    frames = [
        encode_rtu(slave, read(address, quantity, function))
        for slave, function, address, quantity in requests
    ]
    for index, frame in enumerate(frames):
        assume(not any(answers(earlier, frame) for earlier in frames[:index]))
    line = Line()
    stream = b"".join(frames)
    now = 1.0
    start = 0
    for cut in sorted({min(cut, len(stream)) for cut in cuts} | {len(stream)}):
        piece = stream[start:cut]
        now += len(piece) * CHAR
        line.receive(piece, now)
        start = cut
    assert line.foreign_notes() == len(requests)


def test_a_tcp_line_has_no_foreign_masters() -> None:
    """Answers on an MBAP line carry their transaction ids: nothing there is framed as RTU."""
    config = LineConfig(name="t", device="/dev/null", kind="tcp", host="h", port=502)
    line = LineHarness(LineCore(config, -1.0, framing=mbap_framing()))
    line.receive(encode_rtu(7, read(0, 2)), 1.0)
    assert line.notes(LineEvent.FOREIGN_MASTER) == [] and not line.core.shared


def test_a_request_whose_first_bytes_check_as_an_empty_answer_is_heard() -> None:
    """Found by the test above: ``03 04 00 83 00`` checks as an FC 4 answer with a byte
    count of 0 (its CRC matches by chance), which would hide the request to slave 3 that
    those bytes begin. No function answers with a byte count of 0."""
    line = Line()
    stream = encode_rtu(3, read(0, 1, 1)) + encode_rtu(3, read(131, 1, 4))
    line.receive(stream, 1.0 + len(stream) * CHAR)
    assert line.foreign_notes() == 2


def test_a_slave_answering_a_write_with_the_value_it_stored_is_no_second_master() -> None:
    """Some slaves answer an FC 6 write with the value they actually stored (clamped to
    their range), not the exact echo: an intact frame shaped like an FC 6 request, from the
    slave being asked, inside its answer window. It is that slave's malformed answer: the
    line is not marked shared (an active gateway of a pair would step down for it), and
    the write is answered 0x0B once its wait is over, never OK."""
    line = Line(retries=0)
    write = line.submit(1, bytes.fromhex("0600010100"), 0.0)  # write 0x0100
    sent = line.frames()
    assert sent == [encode_rtu(1, bytes.fromhex("0600010100"))]
    clamped = encode_rtu(1, bytes.fromhex("06000100ff"))  # it stored 0x00FF
    line.receive(clamped, 0.02)
    assert line.foreign_notes() == 0 and not line.core.shared
    assert line.core.last_master_frame_at is None
    line.timer()
    assert line.answer_of(write)[1] is Outcome.TARGET_FAILED
    assert not line.core.shared
    # A request frame to another slave is another master's, as before.
    line.receive(encode_rtu(7, read(0, 2)), 3.0)
    assert line.core.shared


def test_a_request_whose_first_bytes_pass_for_another_answer_is_heard_as_a_request() -> None:
    """``04 01 02 A0 00 0D FC 00`` (read 13 coils at 672) starts with seven bytes whose CRC
    also checks as an FC 1 answer of two bytes. After a read of one coil of slave 4, the
    answer is six bytes long: the frame is the next master's request, not that answer."""
    line = Line()
    first, second = encode_rtu(4, read(0, 1, 1)), encode_rtu(4, read(672, 13, 1))
    assert crc16(second[:7]) == 0  # the coincidence itself
    line.receive(first + second, 1.0 + len(first + second) * CHAR)
    assert line.foreign_notes() == 2
