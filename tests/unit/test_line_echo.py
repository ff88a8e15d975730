"""``echo = true``: the core drops the echo of its own frame, exactly those bytes."""

from __future__ import annotations

import struct

import pytest

from gateway.config import LineConfig
from gateway.core.ascii import encode_ascii
from gateway.core.framing import ASCII, RTU, Framing
from gateway.core.line import LineCore, LineRequest
from gateway.core.outcome import LineEvent, Outcome

READ = struct.pack(">BHH", 3, 0, 2)
ANSWER = bytes.fromhex("0304000A000B")
WRITE = bytes.fromhex("0600010003")  # its normal answer is its own echo


class Line:
    def __init__(self, framing: Framing = RTU, echo: bool = True) -> None:
        kind = "ascii" if framing is ASCII else "rtu"
        config = LineConfig(
            name="e", device="/dev/null", baudrate=19200, timeout=0.5, retries=0, echo=echo,
            kind=kind, data_bits=8, parity="N",
        )  # fmt: skip
        self.framing = framing
        self.core = LineCore(config, -1.0, framing=framing)
        self.core.port_opened(-1.0)
        self.answers: list[tuple[bytes, str]] = []

    def submit(self, pdu: bytes, now: float, unit: int = 1) -> bytes:
        def reply(answer: bytes, outcome: str) -> None:
            self.answers.append((answer, outcome))

        self.core.submit(LineRequest(unit, pdu, "m", reply, broadcast=unit == 0), now)
        self.flush()
        frames = [transmit.frame for transmit in self.core.transmits]
        self.core.transmits.clear()
        assert len(frames) == 1
        return frames[0]

    def receive(self, data: bytes, now: float) -> None:
        self.core.receive(data, now)
        self.flush()

    def flush(self) -> None:
        for delivery in self.core.deliveries:
            delivery.request.reply(delivery.pdu, delivery.outcome)
        self.core.deliveries.clear()

    def discarded(self) -> list[str]:
        return [n.detail for n in self.core.notes if n.event is LineEvent.DISCARDED]


@pytest.mark.parametrize("framing", [RTU, ASCII], ids=["rtu", "ascii"])
@pytest.mark.parametrize("cut", [0, 1, 3, 7])
def test_the_echo_is_dropped_however_it_is_split(framing: Framing, cut: int) -> None:
    line = Line(framing)
    frame = line.submit(READ, 0.0)
    answer = framing.encode(1, ANSWER)
    stream = frame + answer
    line.receive(stream[:cut], 0.001)
    line.receive(stream[cut : len(frame) + 2], 0.002)
    assert line.answers == []
    line.receive(stream[len(frame) + 2 :], 0.01)
    assert line.answers == [(ANSWER, Outcome.OK)]
    assert line.discarded() == []


def test_a_write_whose_answer_is_its_echo_waits_for_the_slave() -> None:
    line = Line()
    frame = line.submit(WRITE, 0.0)
    line.receive(frame, 0.001)  # our echo: not the slave's answer, however alike
    assert line.answers == []
    line.receive(frame, 0.01)  # the slave's answer: the same bytes
    assert line.answers == [(WRITE, Outcome.OK)]


def test_without_echo_set_the_echo_of_a_write_would_be_taken_for_its_answer() -> None:
    line = Line(echo=False)
    frame = line.submit(WRITE, 0.0)
    line.receive(frame, 0.001)
    assert line.answers == [(WRITE, Outcome.OK)]  # what echo = true exists to prevent


def test_the_echo_of_a_broadcast_is_not_counted_as_late_bytes() -> None:
    line = Line()
    frame = line.submit(WRITE, 0.0, unit=0)
    line.receive(frame, 0.001)
    assert line.discarded() == []
    line.receive(b"\x01", 0.002)  # anything after it is
    assert line.discarded() == ["late"]


def test_bytes_that_are_not_the_echo_are_the_lines() -> None:
    line = Line(ASCII)
    line.submit(READ, 0.0)
    answer = encode_ascii(1, ANSWER)  # an adapter that suppresses its echo after all
    line.receive(answer, 0.01)
    assert line.answers == [(ANSWER, Outcome.OK)]


def test_a_slave_talking_over_our_frame_does_not_make_the_echo_an_answer() -> None:
    """An earlier request's late answer arrives before our echo: the echo is still dropped."""
    line = Line()
    frame = line.submit(WRITE, 0.0)
    line.receive(bytes.fromhex("0103020001") + b"\x79\x84", 0.001)  # a late FC 3 answer
    line.receive(frame, 0.002)  # then our echo
    assert line.answers == []
    line.receive(frame, 0.01)  # the slave's answer
    assert line.answers == [(WRITE, Outcome.OK)]


@pytest.mark.parametrize("noise", [b"\x01", b"\x01\x06"])
def test_noise_that_looks_like_the_echos_start_does_not_make_the_echo_an_answer(
    noise: bytes,
) -> None:
    """Found by the line core's stateful test: noise that happens to be our frame's first
    bytes was taken for the start of the echo; the echo itself, then not recognised, was
    taken for the write's answer, before the slave had answered (or when it never did)."""
    line = Line()
    frame = line.submit(WRITE, 0.0)
    line.receive(noise, 0.0)  # on the line as our frame goes out
    line.receive(frame, 0.001)  # then our echo, whole
    assert line.answers == []
    line.receive(frame, 0.01)  # the slave's answer
    assert line.answers == [(WRITE, Outcome.OK)]


def test_noise_like_the_echos_start_then_the_echo_in_pieces() -> None:
    line = Line()
    frame = line.submit(WRITE, 0.0)
    line.receive(frame[:1], 0.0)  # noise
    line.receive(frame[:3], 0.0005)  # the echo, in two pieces
    line.receive(frame[3:], 0.001)
    assert line.answers == []
    line.receive(frame, 0.01)
    assert line.answers == [(WRITE, Outcome.OK)]
