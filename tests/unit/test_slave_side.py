"""What the serial-slave listener hears: ASCII frames, requests told from answers, its own echo."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.ascii import MAX_ASCII_FRAME, encode_ascii
from gateway.core.slave_side import (
    AsciiRequestReader,
    FrameFault,
    OwnEcho,
    heard_ascii_request,
    request_or_none,
)
from tests.helpers import h


def test_the_specification_vector() -> None:
    reader = AsciiRequestReader()
    assert reader.feed(b":010100020010EC\r\n") == [b":010100020010EC\r\n"]
    assert heard_ascii_request(b":010100020010EC\r\n") == (1, h("01 0002 0010"))
    assert heard_ascii_request(b":1103006B00037E\r\n") == (0x11, h("03 006B 0003"))
    assert heard_ascii_request(b":1103006b00037e\r\n") == (0x11, h("03 006B 0003"))


def test_characters_outside_a_frame_are_ignored_and_frames_split_anywhere() -> None:
    reader = AsciiRequestReader()
    assert reader.feed(b"noise\r\n\x00\xff:0101") == []
    assert reader.in_frame and reader.buffered == 5
    assert reader.feed(b"00020010EC\r") == []
    assert reader.feed(b"\n:01") == [b":010100020010EC\r\n"]
    assert reader.in_frame and reader.buffered == 3


def test_a_colon_in_mid_frame_restarts_it() -> None:
    reader = AsciiRequestReader()
    frame = encode_ascii(1, h("03 0000 0001"))
    assert reader.feed(b":0103" + frame) == [FrameFault.RESTARTED, frame]
    assert reader.feed(b":01:") == [FrameFault.RESTARTED]
    assert reader.feed(frame[1:]) == [frame]


def test_at_most_513_characters() -> None:
    reader = AsciiRequestReader()
    longest = b":" + b"0" * (MAX_ASCII_FRAME - 3) + b"\r\n"  # 513 characters: a frame
    assert reader.feed(longest) == [longest]
    assert reader.feed(b":" + b"0" * (MAX_ASCII_FRAME - 2)) == []  # 512: still waiting
    assert reader.buffered == MAX_ASCII_FRAME - 1
    assert reader.feed(b"\r\n") == [FrameFault.OVERSIZE]  # 514 with its LF
    assert not reader.in_frame
    assert reader.feed(b"00\r\n") == []  # the rest of the oversized frame: ignored
    assert reader.feed(b":" + b"1" * 600 + b":01") == [FrameFault.OVERSIZE]
    assert reader.in_frame and reader.buffered == 3  # the ':' after it began a new frame


def test_the_inter_character_timeout_abandons_a_frame() -> None:
    reader = AsciiRequestReader()
    assert reader.timed_out() is None  # outside a frame: nothing to abandon
    reader.feed(b":0103")
    assert reader.timed_out() is FrameFault.INCOMPLETE
    assert not reader.in_frame
    assert reader.feed(b"00000001FB\r\n") == []  # the rest, without its ':'


def test_damaged_frames_and_answers_of_other_slaves() -> None:
    assert heard_ascii_request(b":010300000001FC\r\n") is FrameFault.BAD_CHECK  # LRC FB
    assert heard_ascii_request(b":0103FC\r\n") is None  # a request of another shape
    assert heard_ascii_request(b":01FF\r\n") is FrameFault.BAD_CHECK  # too short
    assert heard_ascii_request(b":01030000000G\r\n") is FrameFault.BAD_CHAR
    assert heard_ascii_request(b":010300000001FB\n") is FrameFault.BAD_CHAR  # LF without CR
    assert heard_ascii_request(b":0103000000001FB\r\n") is FrameFault.BAD_CHAR  # odd length
    # Another slave's answer on the bus: intact, but not a request's length.
    assert heard_ascii_request(encode_ascii(1, h("03 02 0000"))) is None
    assert heard_ascii_request(encode_ascii(0, h("06 0001 0003"))) == (0, h("06 0001 0003"))
    # Lengths the function code does not tell are served as they come (user codes).
    assert request_or_none(1, h("41 0102")) == (1, h("41 0102"))
    assert request_or_none(1, h("08 0000 A537")) == (1, h("08 0000 A537"))
    assert request_or_none(1, h("08 0000")) is None


def test_own_echo_is_dropped_exactly_whatever_the_split() -> None:
    echo = OwnEcho()
    assert echo.strip(b"abc") == b"abc"  # nothing sent: nothing to drop
    answer = h("01 06 0064 0007 C9D7")
    echo.sent(answer)
    assert echo.strip(answer[:3]) == b""
    assert echo.expected == len(answer) - 3
    assert echo.strip(answer[3:] + b"\x01\x03") == b"\x01\x03"  # what follows is the line's
    assert echo.expected == 0
    echo.sent(answer)
    assert echo.strip(b"\xff" + answer) == b"\xff" + answer  # not our echo: the line's
    assert echo.strip(answer) == b""  # the echo still expected after those bytes
    echo.sent(b"new")
    assert echo.strip(answer) == answer  # a newer answer replaces the echo expected


def test_noise_like_the_echos_start_does_not_let_the_echo_through_as_a_request() -> None:
    """A noise byte equal to our answer's first byte was taken for the echo's start; the
    echo, then not recognised, went to the request reader: the echo of an FC 6 answer is
    that write's request, executed a second time."""
    echo = OwnEcho()
    answer = h("01 06 0064 0007 C9D7")
    echo.sent(answer)
    assert echo.strip(answer[:1]) == b""  # noise, taken for the echo's first byte
    assert echo.strip(answer) == answer[:1]  # the echo: dropped; the noise is the line's
    assert echo.expected == 0
    echo.sent(answer)
    assert echo.strip(answer[:2]) == b""
    assert echo.strip(answer[:4]) == answer[:2]  # the echo again, in pieces
    assert echo.strip(answer[4:]) == b""
    assert echo.expected == 0


REQUESTS = [
    (1, h("03 0000 000A")), (0x11, h("01 0013 0013")), (1, h("10 0001 0002 04 000A 0102")),
    (1, h("0F 0013 000A 02 CD01")), (1, h("2B 0E 01 00")), (1, h("08 0000 A537")), (1, h("07")),
    (0, h("06 0001 0003")), (247, h("17 0003 0006 000E 0003 06 00FF 00FF 00FF")),
]  # fmt: skip


@given(
    picks=st.lists(st.sampled_from(REQUESTS), min_size=1, max_size=8),
    noise=st.binary(max_size=20).map(lambda b: b.replace(b":", b"")),
    cuts=st.lists(st.integers(min_value=1, max_value=40), max_size=30),
)
def test_round_trip_under_any_chunking(
    picks: list[tuple[int, bytes]], noise: bytes, cuts: list[int]
) -> None:
    stream = noise + b"".join(encode_ascii(unit, pdu) + noise for unit, pdu in picks)
    reader = AsciiRequestReader()
    events: list[bytes | FrameFault] = []
    at = 0
    for size in [*cuts, len(stream)]:
        events += reader.feed(stream[at : at + size])
        at += size
    heard = [heard_ascii_request(e) if isinstance(e, bytes) else e for e in events]
    assert heard == picks


@given(st.lists(st.binary(max_size=700), max_size=12))
def test_any_bytes_stay_bounded_and_yield_only_frames_or_faults(chunks: list[bytes]) -> None:
    reader = AsciiRequestReader()
    for chunk in chunks:
        for event in reader.feed(chunk):
            if isinstance(event, FrameFault):
                continue
            assert event.startswith(b":") and event.endswith(b"\n")
            assert len(event) <= MAX_ASCII_FRAME
            heard = heard_ascii_request(event)
            assert heard is None or isinstance(heard, (FrameFault, tuple))
        assert reader.buffered <= MAX_ASCII_FRAME - 1
