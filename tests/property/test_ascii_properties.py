"""ASCII properties: encode/decode round trip under any chunking and with noise before the
frame, the 513-character bound, and a decoder that fails only inside the ProtocolError family."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.ascii import MAX_ASCII_FRAME, AsciiResponseDecoder, decode_ascii, encode_ascii
from gateway.core.errors import ResponseError
from gateway.core.rtu import RtuFrame
from tests.property.test_rtu_properties import Exchange, exchanges, split

SETTINGS = settings(max_examples=200, deadline=None)

#: Characters a line may carry outside a frame: anything but ':' (which starts one).
_NOISE = st.binary(max_size=20).map(lambda data: data.replace(b":", b""))


def feed_all(decoder: AsciiResponseDecoder, chunks: list[bytes]) -> RtuFrame | None:
    frame = None
    for chunk in filter(None, chunks):
        assert frame is None, "bytes after the frame's LF"
        frame = decoder.feed(chunk)
    return frame


@SETTINGS
@given(exchanges(), st.integers(0, 247), st.lists(st.integers(0, 600), max_size=12), _NOISE)
def test_round_trip_under_any_chunking(
    exchange: Exchange, unit: int, cuts: list[int], noise: bytes
) -> None:
    wire = encode_ascii(unit, exchange.response)
    assert len(wire) == 1 + 2 * (len(exchange.response) + 2) + 2
    decoder = AsciiResponseDecoder(unit, exchange.request)
    frame = feed_all(decoder, split(noise + wire, cuts))
    if len(wire) <= MAX_ASCII_FRAME:
        assert frame == RtuFrame(unit, exchange.response)
        assert decoder.leftover == b""
        assert decode_ascii(wire) == frame


@SETTINGS
@given(exchanges(), st.integers(0, 247), st.binary(min_size=1, max_size=40), st.data())
def test_a_colon_inside_a_frame_starts_it_again(
    exchange: Exchange, unit: int, junk: bytes, data: st.DataObject
) -> None:
    """A broken frame's characters before the answer's ':' never spoil the answer."""
    wire = encode_ascii(unit, exchange.response)
    broken = b":" + junk.replace(b":", b"").replace(b"\n", b"")
    decoder = AsciiResponseDecoder(unit, exchange.request)
    stream = broken + wire
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=6))
    frames: list[RtuFrame] = []
    errors: list[str] = []
    pending = split(stream, cuts)
    while pending:
        chunk = pending.pop(0)
        try:
            frame = decoder.feed(chunk)
        except ResponseError as error:
            errors.append(error.kind)
            leftover = decoder.leftover
            decoder.reset()
            if leftover:
                pending.insert(0, leftover)
            continue
        if frame is not None:
            frames.append(frame)
    if len(wire) <= MAX_ASCII_FRAME:
        assert frames == [RtuFrame(unit, exchange.response)]
        assert errors == ["restarted"]


@SETTINGS
@given(st.binary(max_size=700), st.lists(st.integers(0, 700), max_size=8))
def test_any_bytes_fail_only_with_response_errors(data: bytes, cuts: list[int]) -> None:
    decoder = AsciiResponseDecoder(1, bytes.fromhex("0300000001"))
    for chunk in split(data, cuts):
        try:
            decoder.feed(chunk)
        except ResponseError:
            leftover = decoder.leftover
            decoder.reset()
            if leftover:
                try:
                    decoder.feed(leftover)
                except ResponseError:
                    decoder.reset()
        assert decoder.buffered <= MAX_ASCII_FRAME


@SETTINGS
@given(st.integers(MAX_ASCII_FRAME - 1, MAX_ASCII_FRAME + 40))
def test_frames_longer_than_513_characters_are_refused(length: int) -> None:
    body = b"0" * (length - 3)
    stream = b":" + body + b"\r\n"
    decoder = AsciiResponseDecoder(1, bytes.fromhex("0300000001"))
    try:
        decoder.feed(stream)
    except ResponseError as error:
        assert length > MAX_ASCII_FRAME or error.kind != "oversize"
    else:
        raise AssertionError("a frame of zeros is never a valid answer")
