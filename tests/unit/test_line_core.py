"""The line core with literal times: no event loop, no port, no sleeping.

Each test drives ``LineCore`` the way the driver does (``submit``, ``receive``,
``handle_timer`` with a ``now``) and reads its decisions: the frames it writes,
the answers it delivers, the deadline it asks for.
"""

from __future__ import annotations

import struct
from dataclasses import replace
from typing import Any

import pytest

from gateway.config import LineConfig
from gateway.core.framing import mbap_framing
from gateway.core.line import LineCore, LineRequest, answer_signature, no_reply
from gateway.core.outcome import LineEvent, Outcome, SlaveState
from gateway.core.rtu import encode_rtu
from gateway.core.timing import character_time
from tests.helpers import read
from tests.line_harness import LineHarness

BAUD = 19200
CHAR = character_time(BAUD, 8, "N", 1)
GAP = LineConfig(name="t", device="/dev/null", baudrate=BAUD).gap  # t3.5


def registers_answer(slave: int, request: bytes, first: int) -> bytes:
    """A normal FC 3/4 answer whose first register is ``first`` (the rest count up)."""
    quantity = (request[3] << 8) | request[4]
    values = [(first + index) & 0xFFFF for index in range(quantity)]
    pdu = bytes((request[0], 2 * quantity)) + struct.pack(f">{quantity}H", *values)
    return encode_rtu(slave, pdu)


class Line(LineHarness):
    """A serial line's core, the frames it sent and the answers it delivered."""

    def __init__(self, **settings: Any) -> None:
        defaults: dict[str, Any] = {"baudrate": BAUD, "timeout": 0.5, "retries": 1}
        self.config = LineConfig(name="t", device="/dev/null", **{**defaults, **settings})
        super().__init__(LineCore(self.config, -1.0))

    def sent(self) -> list[bytes]:
        return self.frames()


def tx_time(frame: bytes) -> float:
    return len(frame) * CHAR


# --------------------------------------------------------------------------- the common case


def test_a_read_goes_at_once_and_its_answer_comes_back() -> None:
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    assert line.sent() == [encode_rtu(1, read(100, 2))]
    assert line.core.get_timer() == pytest.approx(tx_time(encode_rtu(1, read(100, 2))) + 0.5)
    line.receive(registers_answer(1, read(100, 2), 100), 0.01)
    pdu, outcome = line.answer_of(request)
    assert outcome == Outcome.OK
    assert pdu == registers_answer(1, read(100, 2), 100)[1:-2]


def test_request_frames_are_encoded_once_and_stay_exact_past_the_cache_bound() -> None:
    """Frames are kept per (slave, PDU) up to a bound; every frame sent is still the request's."""
    from gateway.core.line import FRAME_CACHE_SIZE

    line = Line()
    now = 0.0
    # Past the bound, then the same PDUs again to the same and to another slave.
    pairs = [(1, address) for address in range(FRAME_CACHE_SIZE + 40)]
    pairs += [(1, 300), (2, 300), (1, 0), (3, 0), (1, 0)]
    for slave, address in pairs:
        line.submit(slave, read(address, 2), now)
        (frame,) = line.sent()
        assert frame == encode_rtu(slave, read(address, 2))
        now += tx_time(frame) + 0.001
        line.receive(registers_answer(slave, read(address, 2), address), now)
        now += GAP
    assert [outcome for [(_, outcome)] in line.answers.values()] == [Outcome.OK] * len(pairs)
    assert 0 < len(line.core._frames or {}) <= FRAME_CACHE_SIZE


def test_nothing_is_sent_before_the_gap_after_the_last_byte() -> None:
    line = Line()
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    line.submit(1, read(200, 2), 0.001)
    assert line.sent() == []  # one transaction at a time
    line.receive(registers_answer(1, read(100, 2), 100), 0.010)
    assert line.sent() == []
    assert line.core.get_timer() == pytest.approx(0.010 + GAP)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(200, 2))]


def test_an_answer_during_the_requests_own_transmission_does_not_shorten_the_gap() -> None:
    """An answer can complete before the request has left the wire (a late answer to an
    earlier attempt of the same request, on a full-duplex line): the next frame still waits
    for the request's own end plus the gap, or the two frames would run together."""
    line = Line(frame_gap=0.0, timeout=0.1, retries=1, dead_after=0, late_answer_window=1.0)
    line.submit(1, read(1, 2), 0.0)
    line.submit(1, read(2, 3), 0.0, master="b")
    line.sent()
    retry_at = line.timer()  # timeout: the retry goes (exempt from its own window)
    [retry] = line.sent()
    line.receive(registers_answer(1, read(1, 2), 1), retry_at + 0.0001)  # the first answer
    assert line.sent() == []
    assert line.core.get_timer() == pytest.approx(retry_at + tx_time(retry))
    line.timer()
    assert line.sent() == [encode_rtu(1, read(2, 3))]


def test_bytes_on_an_idle_line_are_discarded_and_postpone_the_next_frame() -> None:
    line = Line()
    line.receive(b"\x01\x02\x03", 1.0)
    assert [note.detail for note in line.notes(LineEvent.DISCARDED)] == ["late"]
    line.submit(1, read(100, 2), 1.0005)
    assert line.sent() == []
    assert line.core.get_timer() == pytest.approx(1.0 + GAP)


# --------------------------------------------------------------------------- retries


@pytest.mark.parametrize(
    ("pdu", "retried"),
    [
        (read(1, 2), True),
        (read(1, 2, 4), True),
        (bytes.fromhex("0800000000"), True),  # diagnostics 0: return query data
        (bytes.fromhex("2b0e0100"), True),  # read device identification
        (bytes.fromhex("11"), True),  # report server id
        (bytes.fromhex("0600010003"), False),  # write single register
        (bytes.fromhex("0800010000"), False),  # diagnostics 1: restart communications
        (bytes.fromhex("08000a0000"), False),  # diagnostics 10: clear counters
        (bytes.fromhex("1700000001000000010200aa"), False),  # FC 23 writes
        (bytes.fromhex("41010203"), False),  # user-defined
        (bytes.fromhex("64"), False),  # user-defined
    ],
)
def test_only_requests_without_side_effects_are_retried(pdu: bytes, retried: bool) -> None:
    line = Line(timeout=0.1, retries=2, dead_after=0)
    request = line.submit(1, pdu, 0.0)
    frames = line.sent()
    while 0 not in line.answers:
        line.timer()
        frames += line.sent()
    assert len(frames) == (3 if retried else 1)
    assert line.answer_of(request) == (bytes((pdu[0] | 0x80, 0x0B)), Outcome.TARGET_FAILED)


def test_retry_unsafe_retries_writes() -> None:
    line = Line(timeout=0.1, retries=1, retry_unsafe=True, dead_after=0)
    line.submit(1, bytes.fromhex("0600010003"), 0.0)
    line.sent()
    line.timer()
    assert line.sent() == [encode_rtu(1, bytes.fromhex("0600010003"))]


def test_a_damaged_answer_is_retried_at_once_without_a_window() -> None:
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    line.sent()
    damaged = bytearray(registers_answer(1, read(100, 2), 100))
    damaged[-1] ^= 0xFF
    line.receive(bytes(damaged), 0.01)
    assert line.notes(LineEvent.LATE_WINDOW) == []
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]
    line.receive(registers_answer(1, read(100, 2), 100), 0.03)
    assert line.answer_of(request)[1] == Outcome.OK


def test_after_a_garbled_frame_the_answer_behind_it_is_taken_within_twice_the_silence() -> None:
    """A whole frame of another unit with a bad CRC may be noise in front of the answer."""
    line = Line()
    silence = line.config.silence
    request = line.submit(1, read(100, 2), 0.0)
    line.sent()
    line.receive(bytes.fromhex("02 03 02 0000 0000"), 0.010)  # bad CRC, not the answer's unit
    assert line.core.get_timer() == pytest.approx(0.010 + 2 * silence)
    line.receive(registers_answer(1, read(100, 2), 100), 0.010 + 1.9 * silence)
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.sent() == []  # taken without a retry


def test_after_a_garbled_frame_and_twice_the_silence_of_quiet_the_request_is_retried() -> None:
    line = Line()
    silence = line.config.silence
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    line.receive(bytes.fromhex("02 03 02 0000 0000"), 0.010)
    line.timer(0.010 + 1.9 * silence)
    assert line.sent() == []  # still listening for the answer behind the garbage
    assert line.timer() == pytest.approx(0.010 + 2 * silence)  # quiet since the garbage
    sent = line.sent()
    if not sent:
        line.timer()  # the frame gap, if any is left
        sent = line.sent()
    assert sent == [encode_rtu(1, read(100, 2))]


def test_noise_right_before_the_answer_is_skipped_and_the_answer_taken() -> None:
    """A transceiver turning around puts a byte on the line just before the answer."""
    line = Line()
    request = line.submit(1, read(100, 2), 0.0)
    line.sent()
    line.receive(b"\xff" + registers_answer(1, read(100, 2), 100), 0.010)
    assert line.answer_of(request) == (bytes.fromhex("03 04 0064 0065"), Outcome.OK)
    assert [n.detail for n in line.notes(LineEvent.DISCARDED)] == ["noise"]
    assert line.notes(LineEvent.RETRY) == []
    assert line.notes(LineEvent.CRC_ERROR) == []  # noise is not a damaged answer


def test_a_burst_of_noise_ended_by_silence_leaves_the_wait_for_the_answer_as_it_was() -> None:
    """Too short to be any answer: the attempt keeps its deadline, so a slave answering
    long after the noise is heard, not talked over by a retry."""
    line = Line()
    silence = line.config.silence
    request = line.submit(1, read(100, 2), 0.0)
    line.sent()
    deadline = line.core.get_timer()
    line.receive(bytes.fromhex("FF 00 55"), 0.002)  # a length nobody can tell: silence ends it
    assert line.timer() == pytest.approx(0.002 + silence)
    assert [n.detail for n in line.notes(LineEvent.DISCARDED)] == ["noise"]
    assert line.core.get_timer() == deadline
    line.receive(registers_answer(1, read(100, 2), 100), 0.002 + 20 * silence)
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.sent() == []


# --------------------------------------------------------------------------- late answers


def test_a_late_answer_never_reaches_a_read_that_looks_like_the_lost_one() -> None:
    line = Line(timeout=0.5, retries=0, late_answer_window=2.0)
    lost = line.submit(1, read(100, 2), 0.0)
    line.sent()
    failed_at = line.timer()  # the timeout
    assert line.answer_of(lost)[1] == Outcome.TARGET_FAILED
    # Same slave, function and byte count: could take the late answer for its own.
    held = line.submit(1, read(200, 2), failed_at + 0.01)
    # Another slave is served meanwhile.
    other = line.submit(2, read(200, 2), failed_at + 0.02)
    assert line.sent() == [encode_rtu(2, read(200, 2))]
    line.receive(registers_answer(2, read(200, 2), 7), failed_at + 0.05)
    assert line.answer_of(other)[1] == Outcome.OK
    # The late answer to the lost request arrives while the line is idle: thrown away.
    line.core.handle_timer(failed_at + 0.06)
    assert line.sent() == []
    line.receive(registers_answer(1, read(100, 2), 100), failed_at + 0.30)
    assert requests_answered(line) == {0, 2}
    # It completes the lost answer: nothing more is coming, the held read may go now.
    line.timer()
    assert line.sent() == [encode_rtu(1, read(200, 2))]
    line.receive(registers_answer(1, read(200, 2), 200), failed_at + 0.40)
    assert line.answer_of(held) == (registers_answer(1, read(200, 2), 200)[1:-2], Outcome.OK)


def requests_answered(line: Line) -> set[int]:
    return set(line.answers)


def test_the_window_waits_for_the_answers_of_every_lost_attempt() -> None:
    """Both attempts of a read time out; the first attempt's answer arriving does not end the
    window, since the second attempt's answer is still on its way."""
    line = Line(timeout=0.1, retries=1, late_answer_window=2.0, dead_after=0)
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    line.timer()  # first timeout: the retry goes
    assert line.sent() == [encode_rtu(1, read(100, 2))]
    failed_at = line.timer()  # second timeout: 0x0B
    assert line.answer_of(line.requests[0])[1] == Outcome.TARGET_FAILED
    held = line.submit(1, read(200, 2), failed_at + 0.01)
    line.receive(registers_answer(1, read(100, 2), 100), failed_at + 0.05)  # the first answer
    line.core.handle_timer(failed_at + 0.06)
    assert line.sent() == []  # the second is still to come
    line.receive(registers_answer(1, read(100, 2), 100), failed_at + 0.10)  # the second answer
    line.timer()
    assert line.sent() == [encode_rtu(1, read(200, 2))]
    line.receive(registers_answer(1, read(200, 2), 200), failed_at + 0.2)
    assert line.answer_of(held) == (registers_answer(1, read(200, 2), 200)[1:-2], Outcome.OK)


def test_a_late_answer_during_another_slaves_transaction_ends_the_window() -> None:
    """The lost answer arrives while another slave's request is on the wire: discarded there,
    it still tells the line that slave 1 is alive and done, so it is served again at once."""
    line = Line(timeout=0.5, retries=0, late_answer_window=2.0)
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    failed_at = line.timer()
    assert line.core.slave_state(1) is SlaveState.SUSPECT
    other = line.submit(2, read(7, 2), failed_at + 0.01)
    held = line.submit(1, read(200, 2), failed_at + 0.01, master="b")
    assert line.sent() == [encode_rtu(2, read(7, 2))]
    line.receive(registers_answer(1, read(100, 2), 100), failed_at + 0.02)  # slave 1, late
    assert [n.detail for n in line.notes(LineEvent.DISCARDED)][-1] == "unexpected_unit"
    assert line.core.slave_state(1) is SlaveState.UP
    line.receive(registers_answer(2, read(7, 2), 7), failed_at + 0.03)
    assert line.answer_of(other)[1] == Outcome.OK
    line.timer()
    assert line.sent() == [encode_rtu(1, read(200, 2))]
    line.receive(registers_answer(1, read(200, 2), 200), failed_at + 0.1)
    assert line.answer_of(held) == (registers_answer(1, read(200, 2), 200)[1:-2], Outcome.OK)


def test_a_distinguishable_read_goes_and_its_answer_ends_the_window() -> None:
    line = Line(timeout=0.5, retries=0, late_answer_window=2.0, dead_after=0)
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    failed_at = line.timer()
    line.submit(1, read(100, 2), failed_at)  # held
    line.submit(1, read(100, 3), failed_at)  # 6 bytes, not 4: distinguishable
    assert line.sent() == [encode_rtu(1, read(100, 3))]
    # The late 4-byte answer arrives first: discarded, the wait goes on.
    line.receive(registers_answer(1, read(100, 2), 1), failed_at + 0.1)
    assert [n.detail for n in line.notes(LineEvent.DISCARDED)][-1] == "mismatch"
    line.receive(registers_answer(1, read(100, 3), 5), failed_at + 0.2)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]


def test_the_window_ends_on_its_own_and_the_held_read_goes() -> None:
    line = Line(timeout=0.5, retries=0, late_answer_window=1.5, dead_after=0)
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    failed_at = line.timer()
    line.submit(1, read(300, 2), failed_at + 0.01)
    assert line.sent() == []
    assert line.core.get_timer() == pytest.approx(failed_at + 1.5)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(300, 2))]


def test_a_reopened_line_keeps_the_late_answer_windows_of_the_line_it_replaces() -> None:
    """A reload that reopens the port hands the open windows on: the lost answer may come
    through the new port (the same wire), so a read that looks like the lost one waits for
    it there, and a distinguishable one goes at once."""
    old = Line(timeout=0.5, retries=0, late_answer_window=2.0)
    old.submit(1, read(100, 2), 0.0)
    old.sent()
    failed_at = old.timer()
    old.core.stop(failed_at)
    handover = old.core.handover()
    assert [(w.slave, w.until, w.pending) for w in handover.windows] == [(1, failed_at + 2.0, 1)]

    new = Line(timeout=0.5, retries=0, late_answer_window=2.0)
    new.core.take_over(handover, failed_at + 0.1)
    held = new.submit(1, read(200, 2), failed_at + 0.1)
    assert new.sent() == []
    assert new.core.get_timer() == pytest.approx(failed_at + 2.0)
    other = new.submit(1, read(200, 3), failed_at + 0.1, master="b")
    assert new.sent() == [encode_rtu(1, read(200, 3))]
    # The lost answer comes through the new port during b's read: discarded there, and
    # the window ends (every lost attempt's answer has come).
    new.receive(registers_answer(1, read(100, 2), 100), failed_at + 0.2)
    assert [n.detail for n in new.notes(LineEvent.DISCARDED)][-1] == "mismatch"
    new.receive(registers_answer(1, read(200, 3), 3), failed_at + 0.25)
    assert new.answer_of(other)[1] == Outcome.OK
    new.timer()
    assert new.sent() == [encode_rtu(1, read(200, 2))]
    new.receive(registers_answer(1, read(200, 2), 200), failed_at + 0.3)
    assert new.answer_of(held) == (registers_answer(1, read(200, 2), 200)[1:-2], Outcome.OK)
    # Windows that closed before the handover are not kept.
    closed = Line(timeout=0.5)
    closed.core.take_over(handover, failed_at + 2.0)
    closed.submit(1, read(200, 2), failed_at + 2.0)
    assert closed.sent() == [encode_rtu(1, read(200, 2))]


def test_a_modbus_tcp_line_hands_on_no_late_answer_windows() -> None:
    """A lost answer on an MBAP line went with the old connection, and its transaction id
    tells it from another request's anyway: nothing waits on the reopened line."""
    config = LineConfig(name="t", device="/dev/null", kind="tcp", timeout=0.5, retries=0)
    core = LineCore(config, 0.0, framing=mbap_framing())
    core.port_opened(0.0)
    core.submit(LineRequest(1, read(100, 2), "m", lambda answer, outcome: None), 0.0)
    deadline = core.get_timer()
    assert deadline is not None
    core.handle_timer(deadline)
    assert core.handover().windows == ()


def test_an_exception_to_a_read_of_the_same_function_keeps_the_window_open() -> None:
    """An exception answer cannot be told from the lost request's: this read's own answer
    may be the one still coming, so its signature joins the window."""
    line = Line(timeout=0.5, retries=0, late_answer_window=1.0, dead_after=0)
    line.submit(1, read(100, 2), 0.0)
    line.sent()
    failed_at = line.timer()
    line.submit(1, read(100, 3), failed_at)
    line.sent()
    line.receive(encode_rtu(1, bytes.fromhex("8302")), failed_at + 0.1)
    line.submit(1, read(500, 3), failed_at + 0.2)
    assert line.sent() == []  # 3 registers are now held too


def test_answer_signatures() -> None:
    assert answer_signature(read(1, 10)) == answer_signature(read(500, 10))
    assert answer_signature(read(1, 10)) != answer_signature(read(1, 11))
    assert answer_signature(read(1, 10)) != answer_signature(read(1, 10, 4))
    assert answer_signature(bytes.fromhex("0600010003")) != answer_signature(
        bytes.fromhex("0600020003")
    )
    assert answer_signature(bytes.fromhex("41")) == bytes.fromhex("41")


# --------------------------------------------------------------------------- isolation


def test_a_silent_slave_turns_suspect_then_down_and_costs_the_others_little() -> None:
    line = Line(timeout=0.5, retries=1, dead_after=2, late_answer_window=0, probe_interval=2.0)
    first = line.submit(9, read(1, 2), 0.0, master="a")
    line.sent()
    healthy = line.submit(1, read(1, 2), 0.1, master="c")
    now = line.timer()  # timeout: suspect
    assert line.core.slave_state(9) is SlaveState.SUSPECT
    # A healthy slave's request goes before the suspect slave's retry.
    assert line.sent() == [encode_rtu(1, read(1, 2))]
    # At most one of its requests waits (the retry); the next is answered at once.
    second = line.submit(9, read(2, 2), now, master="b")
    assert line.answer_of(second) == (bytes.fromhex("830b"), Outcome.TARGET_FAILED)
    line.receive(registers_answer(1, read(1, 2), 1), now + 0.01)
    assert line.answer_of(healthy)[1] == Outcome.OK
    # Nothing healthy waits: the retry goes, fails, and the slave is down.
    now = line.timer()
    assert line.sent() == [encode_rtu(9, read(1, 2))]
    now = line.timer()
    assert line.core.slave_state(9) is SlaveState.DOWN
    assert line.answer_of(first)[1] == Outcome.TARGET_FAILED
    down = line.submit(9, read(3, 2), now + 0.1)
    assert line.answer_of(down)[1] == Outcome.TARGET_FAILED
    assert line.sent() == []
    # After the probe interval one request goes as a probe; its answer brings it back.
    probe = line.submit(9, read(4, 2), now + 2.0)
    assert line.sent() == [encode_rtu(9, read(4, 2))]
    line.receive(registers_answer(9, read(4, 2), 4), now + 2.05)
    assert line.answer_of(probe)[1] == Outcome.OK
    assert line.core.slave_state(9) is SlaveState.UP


def test_a_function_the_slave_ignores_does_not_isolate_it() -> None:
    line = Line(timeout=0.2, retries=0, dead_after=1, late_answer_window=0)
    line.submit(1, read(1, 2), 0.0)
    line.sent()
    line.receive(registers_answer(1, read(1, 2), 1), 0.01)
    now = 0.01 + GAP
    for index in range(5):  # FC 65 is never answered by this slave
        line.submit(1, bytes.fromhex("41"), now, master=f"hostile{index}")
        if not line.sent():
            line.timer()  # the gap
            assert line.sent()
        now = line.timer()  # the timeout
    assert line.core.slave_state(1) is SlaveState.UP
    assert len(line.notes(LineEvent.TIMEOUT)) == 5


def test_suspect_slaves_get_at_most_their_share_while_healthy_requests_wait() -> None:
    line = Line(timeout=0.5, retries=0, late_answer_window=0, probe_share=0.05, dead_after=5)
    line.submit(9, read(1, 2), 0.0, master="p")
    line.sent()
    line.submit(1, read(1000, 2), 0.1, master="h")
    now = line.timer()  # timeout: suspect, and 0.5 s of debt on the isolated share
    suspect = line.submit(9, read(2, 2), now, master="p")
    # A healthy master keeps the line busy: each answer 20 ms after its request.
    sent_to_suspect_at: list[float] = []
    for index in range(400):
        line.submit(1, read(index, 2), now, master="h")
        frames = line.sent()
        while not frames:
            now = line.timer()
            frames = line.sent()
        if frames[0][0] == 9:
            sent_to_suspect_at.append(now)
            break
        now += 0.02
        line.receive(registers_answer(1, read(index, 2), index), now)
    # The suspect request expired at its timeout (0x0B), long before the share allowed it.
    assert line.answer_of(suspect)[1] == Outcome.TARGET_FAILED
    assert sent_to_suspect_at == []


# --------------------------------------------------------------------------- fairness and bounds


def test_a_polite_master_is_next_after_a_deep_pipeline() -> None:
    line = Line()
    for index in range(16):
        line.submit(1, read(index, 2), 0.0, master="greedy")
    line.sent()
    polite = line.submit(2, read(7, 2), 0.001, master="polite")
    line.receive(registers_answer(1, read(0, 2), 0), 0.01)
    line.timer()
    assert line.sent() == [encode_rtu(2, read(7, 2))]
    line.receive(registers_answer(2, read(7, 2), 7), 0.02)
    assert line.answer_of(polite)[1] == Outcome.OK


def test_wire_time_not_request_count_is_shared() -> None:
    """A master whose transactions take long gets fewer of them."""
    line = Line(timeout=1.0)
    for index in range(10):
        line.submit(1, read(index, 2), 0.0, master="slow")
        line.submit(2, read(index, 2), 0.0, master="fast")
    order: list[int] = []
    now = 0.0
    for _ in range(12):
        frames = line.sent()
        while not frames:
            now = line.timer()
            frames = line.sent()
        slave = frames[0][0]
        order.append(slave)
        now += 0.2 if slave == 1 else 0.02
        request = read(int.from_bytes(frames[0][2:4], "big"), 2)
        line.receive(registers_answer(slave, request, 0), now)
    assert order.count(2) >= 3 * order.count(1)


def test_a_master_over_its_queue_bound_gets_0x06_and_others_are_untouched() -> None:
    line = Line(max_queue_per_master=4)
    requests = [line.submit(1, read(index, 2), 0.0, master="greedy") for index in range(6)]
    # One on the wire, four waiting: the sixth is over the bound.
    assert line.answer_of(requests[5]) == (bytes.fromhex("8306"), Outcome.BUSY)
    other = line.submit(1, read(99, 2), 0.0, master="other")
    assert line.requests.index(other) not in line.answers


def test_a_full_line_takes_from_the_longest_queue_not_from_a_polite_master() -> None:
    line = Line(max_queue=8, max_queue_per_master=100)
    greedy = [line.submit(1, read(index, 2), 0.0, master="greedy") for index in range(9)]
    polite = line.submit(2, read(1, 2), 0.0, master="polite")
    assert line.requests.index(polite) not in line.answers
    assert line.answer_of(greedy[8]) == (bytes.fromhex("830a"), Outcome.NO_ROUTE)


# --------------------------------------------------------------------------- noise, broadcast, port


def test_a_line_that_never_goes_quiet_answers_0x0b_then_recovers() -> None:
    line = Line(timeout=0.5, noisy_after=1.0)
    request = line.submit(1, read(1, 2), 0.0)
    line.sent()
    line.receive(registers_answer(1, read(1, 2), 1), 0.01)
    waiting = line.submit(1, read(2, 2), 0.011)
    now = 0.011
    while now < 1.5:  # a babbling transceiver: a byte every millisecond
        now += 0.001
        line.receive(b"\xff", now)
        line.core.handle_timer(now)
        line.flush()
    assert line.answer_of(request)[1] == Outcome.OK
    assert line.answer_of(waiting) == (bytes.fromhex("830b"), Outcome.TARGET_FAILED)
    assert line.core.noisy
    assert line.answer_of(line.submit(1, read(3, 2), now))[1] == Outcome.TARGET_FAILED
    line.timer()  # a gap
    assert not line.core.noisy
    line.submit(1, read(4, 2), now + 0.01)
    assert line.sent() == [encode_rtu(1, read(4, 2))]


def test_a_broadcast_is_answered_at_once_and_followed_by_the_turnaround() -> None:
    line = Line(broadcast_turnaround=0.1)
    request = LineRequest(0, bytes.fromhex("0600010003"), "m", lambda pdu, outcome: None, True)
    line.core.submit(request, 0.0)
    [frame] = line.sent()
    assert frame == encode_rtu(0, bytes.fromhex("0600010003"))
    assert line.core.deliveries[0].outcome == Outcome.BROADCAST
    line.flush()
    line.submit(1, read(1, 2), 0.001)
    assert line.sent() == []
    assert line.core.get_timer() == pytest.approx(tx_time(frame) + 0.1 + GAP)


def test_a_reopened_line_keeps_the_turnaround_of_a_broadcast_sent_before() -> None:
    """The old line sent a broadcast and stopped at once (a broadcast leaves nothing on the
    wire to wait for): the slaves still execute it, so the new line waits out the
    turnaround too."""
    old = Line(broadcast_turnaround=0.1)
    old.core.submit(LineRequest(0, bytes.fromhex("0600010003"), "m", no_reply, True), 0.0)
    [frame] = old.sent()
    old.core.stop(0.001)
    assert old.core.idle
    new = Line(broadcast_turnaround=0.1)
    new.core.take_over(old.core.handover(), 0.002)
    new.submit(1, read(1, 2), 0.002)
    assert new.sent() == []
    assert new.core.get_timer() == pytest.approx(tx_time(frame) + 0.1 + GAP)


def test_a_lost_port_answers_everything_0x0a() -> None:
    line = Line()
    on_wire = line.submit(1, read(1, 2), 0.0)
    queued = line.submit(1, read(2, 2), 0.0)
    line.core.port_lost(0.01)
    line.flush()
    assert line.answer_of(on_wire)[1] == Outcome.NO_ROUTE
    assert line.answer_of(queued)[1] == Outcome.NO_ROUTE
    assert line.answer_of(line.submit(1, read(3, 2), 0.02))[1] == Outcome.NO_ROUTE


# --------------------------------------------------------------------------- coalescing, cache


def test_identical_queued_reads_share_one_transaction_but_not_across_a_write() -> None:
    line = Line()
    line.submit(1, read(50, 2), 0.0, master="x")  # on the wire
    first = line.submit(1, read(100, 2), 0.0, master="a")
    joined = line.submit(1, read(100, 2), 0.0, master="b")
    line.submit(1, bytes.fromhex("0600640001"), 0.0, master="c")
    after_write = line.submit(1, read(100, 2), 0.0, master="d")
    assert len(line.notes(LineEvent.COALESCED)) == 1
    assert first.followers == [joined]
    assert after_write not in first.followers


def test_a_reopening_reload_hands_over_every_waiting_request_in_submission_order() -> None:
    """``take_queued`` hands over the reads that joined others as requests of their own, in
    the order the masters submitted them: whoever takes them answers (0x0A) or resubmits each
    one, and nothing waits hidden behind a request the new line lets join another."""
    write = bytes.fromhex("0600640001")
    old = Line()
    old.submit(1, read(50, 2), 0.0, master="x")  # on the wire: stays with the old line
    old.submit(2, read(100, 2), 0.001, master="a")
    old.submit(2, write, 0.002, master="b")
    second = old.submit(2, read(100, 2), 0.003, master="b")  # after b's write: a read of its own
    joined = old.submit(2, read(100, 2), 0.004, master="a")  # joins b's
    assert second.followers == [joined]
    taken = old.core.take_queued()
    assert [request.pdu for request in taken] == [read(100, 2), write, read(100, 2), read(100, 2)]
    assert taken == old.requests[1:] and all(not r.followers for r in taken)
    assert old.core.queued == 0

    new = Line()
    for request in taken:
        new.core.submit(request, 0.01)
    new.flush()
    assert new.sent() == [encode_rtu(2, read(100, 2))]  # the first read; the rest wait
    new.receive(registers_answer(2, read(100, 2), 1), 0.02)
    new.timer()
    assert new.sent() == [encode_rtu(2, write)]
    new.receive(encode_rtu(2, write), 0.03)
    new.timer()
    assert new.sent() == [encode_rtu(2, read(100, 2))]  # second and joined, together again
    new.receive(registers_answer(2, read(100, 2), 2), 0.04)
    answers = [old.answers.get(index, []) for index in range(1, 5)]
    assert [len(answer) for answer in answers] == [1, 1, 1, 1]
    assert [answer[0][1] for answer in answers] == [Outcome.OK] * 4
    assert answers[3] == answers[2] != answers[0]  # joined again: b's read after b's write


def busy_line_after(used: str) -> Line:
    """A line where master ``used`` has had a transaction (so others are due before it) and
    master x's read of slave 2 is on the wire until ``line.receive(... read(60) ...)``."""
    line = Line()
    line.submit(1, read(50, 2), 0.0, master=used)
    line.sent()
    line.receive(registers_answer(1, read(50, 2), 50), 0.01)
    line.submit(2, read(60, 2), 0.02, master="x")
    assert line.sent() == [encode_rtu(2, read(60, 2))]
    return line


def test_a_masters_write_does_not_overtake_its_read_waiting_in_another_masters() -> None:
    """Master a's read joined b's identical queued read; a's later write to that slave waits
    until the shared read has gone, though fair order would have sent a's write first."""
    write = bytes.fromhex("0600640001")
    line = busy_line_after(used="b")  # a is due first
    line.submit(1, read(100, 2), 0.021, master="b")
    joined = line.submit(1, read(100, 2), 0.022, master="a")
    line.submit(1, write, 0.023, master="a")
    line.receive(registers_answer(2, read(60, 2), 60), 0.03)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]  # the shared read, then a's write
    line.receive(registers_answer(1, read(100, 2), 7), 0.05)
    assert line.answer_of(joined)[1] == Outcome.OK
    line.timer()
    assert line.sent() == [encode_rtu(1, write)]


def test_a_masters_read_does_not_join_another_masters_while_its_own_write_waits() -> None:
    """Fair order may send b's read before a's earlier write: a's read after its write must
    not share b's transaction, or its answer would predate its own write."""
    write = bytes.fromhex("0600640001")
    line = busy_line_after(used="a")  # b is due first
    line.submit(1, write, 0.021, master="a")
    shared = line.submit(1, read(100, 2), 0.022, master="b")
    mine = line.submit(1, read(100, 2), 0.023, master="a")
    assert shared.followers == []
    line.receive(registers_answer(2, read(60, 2), 60), 0.03)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]  # b's read, alone
    line.receive(registers_answer(1, read(100, 2), 7), 0.05)
    assert line.answer_of(shared)[1] == Outcome.OK
    assert line.requests.index(mine) not in line.answers
    line.timer()
    assert line.sent() == [encode_rtu(1, write)]
    line.receive(encode_rtu(1, write), 0.07)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]  # a's read, after its write
    line.receive(registers_answer(1, read(100, 2), 8), 0.09)
    assert line.answer_of(mine) == (registers_answer(1, read(100, 2), 8)[1:-2], Outcome.OK)


def test_a_masters_broadcast_does_not_overtake_its_read_waiting_in_another_masters() -> None:
    broadcast = bytes.fromhex("0600010001")
    line = busy_line_after(used="b")  # a is due first
    shared = line.submit(1, read(100, 2), 0.021, master="b")
    joined = line.submit(1, read(100, 2), 0.022, master="a")
    assert shared.followers == [joined]
    line.submit(0, broadcast, 0.023, master="a")
    line.receive(registers_answer(2, read(60, 2), 60), 0.03)
    line.timer()
    assert line.sent() == [encode_rtu(1, read(100, 2))]  # the shared read, then a's broadcast
    line.receive(registers_answer(1, read(100, 2), 7), 0.05)
    assert line.answer_of(joined)[1] == Outcome.OK
    line.timer()
    assert line.sent() == [encode_rtu(0, broadcast)]


def suspect_slave_9(line: Line) -> float:
    """Slave 9 misses one answer (no retry): suspect, its late-answer window open."""
    line.submit(9, read(0, 2), 0.0, master="x")
    assert line.sent() == [encode_rtu(9, read(0, 2))]
    now = line.timer()
    assert line.core.slave_state(9) is SlaveState.SUSPECT
    return now


def test_a_masters_broadcast_waits_for_its_earlier_read_in_the_isolated_lane() -> None:
    broadcast = bytes.fromhex("0600010001")
    line = Line(timeout=0.1, retries=0)
    suspect_slave_9(line)
    line.submit(2, read(60, 2), 0.2, master="y")  # on the wire
    line.sent()
    lane = line.submit(9, read(1, 3), 0.201, master="a")  # waits in the lane
    line.submit(0, broadcast, 0.202, master="a")
    line.receive(registers_answer(2, read(60, 2), 60), 0.21)
    line.timer()
    assert line.sent() == [encode_rtu(9, read(1, 3))]  # a's read, then its broadcast
    line.receive(registers_answer(9, read(1, 3), 1), 0.23)
    assert line.answer_of(lane)[1] == Outcome.OK
    line.timer()
    assert line.sent() == [encode_rtu(0, broadcast)]


def test_a_read_in_the_isolated_lane_waits_for_its_masters_earlier_broadcast() -> None:
    broadcast = bytes.fromhex("0600010001")
    line = Line(timeout=0.1, retries=0, broadcast_turnaround=0.01)
    suspect_slave_9(line)
    line.submit(2, read(60, 2), 5.0, master="y")  # on the wire; the isolated share has recovered
    line.sent()
    line.submit(0, broadcast, 5.001, master="a")
    lane = line.submit(9, read(1, 3), 5.002, master="a")  # waits in the lane
    line.receive(registers_answer(2, read(60, 2), 60), 5.01)
    line.timer(5.02)  # (the window's stale deadline would come first)
    assert line.sent() == [encode_rtu(0, broadcast)]  # a's broadcast, then its read
    line.timer()
    assert line.sent() == [encode_rtu(9, read(1, 3))]
    line.receive(registers_answer(9, read(1, 3), 1), 5.1)
    assert line.answer_of(lane)[1] == Outcome.OK


def test_a_read_back_from_the_lane_stays_behind_its_masters_earlier_broadcast() -> None:
    """The slave's lost answer arrives: it is alive, and the lane's request rejoins its
    master's queue, first, but not before that master's broadcast submitted before it."""
    broadcast = bytes.fromhex("0600010001")
    line = Line(timeout=0.1, retries=0)
    suspect_slave_9(line)
    line.submit(2, read(60, 2), 0.2, master="y")  # on the wire
    line.sent()
    line.submit(0, broadcast, 0.201, master="a")
    lane = line.submit(9, read(1, 3), 0.202, master="a")  # waits in the lane
    line.receive(registers_answer(2, read(60, 2), 60), 0.21)
    line.receive(registers_answer(9, read(0, 2), 0), 0.211)  # x's lost answer: 9 is up again
    assert line.core.slave_state(9) is SlaveState.UP
    line.timer()
    assert line.sent() == [encode_rtu(0, broadcast)]
    line.timer()
    assert line.sent() == [encode_rtu(9, read(1, 3))]
    line.receive(registers_answer(9, read(1, 3), 1), 0.3)
    assert line.answer_of(lane)[1] == Outcome.OK


def test_the_cache_answers_within_max_age_and_a_write_empties_it() -> None:
    from gateway.config import CacheRule

    line = Line(cache=(CacheRule(1, 3, 0, 100, 1.0),))
    line.submit(1, read(10, 2), 0.0)
    line.sent()
    line.receive(registers_answer(1, read(10, 2), 10), 0.01)
    assert line.answer_of(line.submit(1, read(10, 2), 0.5))[1] == Outcome.CACHED
    line.submit(1, bytes.fromhex("06000a0001"), 0.6)
    line.timer()
    line.sent()
    line.receive(encode_rtu(1, bytes.fromhex("06000a0001")), 0.65)
    uncached = line.submit(1, read(10, 2), 0.7)
    assert line.requests.index(uncached) not in line.answers


def test_a_masters_bound_counts_its_request_on_the_wire() -> None:
    """The request on the wire comes back to wait for its retry when it fails: counted from
    the start, it never takes its master past the bound."""
    line = Line(max_queue_per_master=2, timeout=0.1, retries=1, late_answer_window=0)
    on_wire = line.submit(1, read(1, 2), 0.0)
    line.sent()
    line.submit(1, read(2, 2), 0.0)
    refused = line.submit(1, read(3, 2), 0.0)
    assert line.answer_of(refused) == (bytes((0x83, 0x06)), Outcome.BUSY)
    line.timer()  # the timeout: it comes back for its retry
    assert on_wire.attempts == 2
    assert line.core.queued_for("m") <= 2


def test_a_read_answered_while_a_write_waits_is_not_cached() -> None:
    """The read's answer predates the write, which runs after it: cached, it would answer
    the writer's next read (and everyone's until max age) with the value before its write."""
    from gateway.config import CacheRule

    write = bytes.fromhex("06000a0001")
    line = Line(cache=(CacheRule(1, 3, 0, 100, 10.0),))
    line.submit(1, read(10, 2), 0.0, master="a")  # on the wire
    line.sent()
    line.submit(1, write, 0.001, master="b")  # waits for the line
    line.receive(registers_answer(1, read(10, 2), 10), 0.01)
    between = line.submit(1, read(10, 2), 0.011, master="b")  # after its own write: not cached
    assert line.requests.index(between) not in line.answers
    line.timer()
    assert line.sent() == [encode_rtu(1, write)]
    line.receive(encode_rtu(1, write), 0.05)
    later = line.submit(1, read(10, 2), 0.06, master="c")
    assert line.requests.index(later) not in line.answers


def test_a_read_queued_behind_a_write_is_cached_only_after_it() -> None:
    """A write submitted before a read but sent after it (another master's, served later
    by fair order) makes the read's answer stale as soon as it runs."""
    from gateway.config import CacheRule

    write = bytes.fromhex("06000a0001")
    line = Line(cache=(CacheRule(1, 3, 0, 100, 10.0),))
    line.submit(1, read(50, 2), 0.0, master="x")  # on the wire
    line.sent()
    line.submit(1, write, 0.001, master="b")
    line.submit(1, read(10, 2), 0.002, master="a")
    line.receive(registers_answer(1, read(50, 2), 50), 0.01)
    line.timer()
    [first] = line.sent()
    line.receive(
        encode_rtu(1, write)
        if first == encode_rtu(1, write)
        else registers_answer(1, read(10, 2), 10),
        0.03,
    )
    line.timer()
    [second] = line.sent()
    assert {first, second} == {encode_rtu(1, write), encode_rtu(1, read(10, 2))}
    line.receive(
        encode_rtu(1, write)
        if second == encode_rtu(1, write)
        else registers_answer(1, read(10, 2), 10),
        0.06,
    )
    after = line.submit(1, read(10, 2), 0.07, master="c")
    served_from_cache = line.requests.index(after) in line.answers
    assert served_from_cache == (first == encode_rtu(1, write))  # cached only after the write


def test_reconfigure_switching_isolation_off_serves_the_slave_again() -> None:
    line = Line(timeout=0.1, retries=0, dead_after=1, late_answer_window=0)
    line.submit(3, read(1, 2), 0.0)
    line.sent()
    line.timer()
    assert line.core.slave_state(3) is SlaveState.DOWN
    line.core.reconfigure(replace(line.config, dead_after=0), 0.2)
    assert line.core.slave_state(3) is SlaveState.UP
    line.submit(3, read(1, 2), 0.3)
    assert line.sent() == [encode_rtu(3, read(1, 2))]
