"""MBAP decoder properties: round trip, chunking invariance, typed failure, bounded buffer."""

from __future__ import annotations

from itertools import pairwise

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.errors import FramingError
from gateway.core.mbap import MbapDecoder, MbapFrame, encode_mbap

PARTIAL_LIMIT = 259  # a header announcing 254 bytes, with one byte still missing

frames = st.builds(
    MbapFrame,
    transaction_id=st.integers(0, 0xFFFF),
    unit_id=st.integers(0, 0xFF),
    pdu=st.binary(min_size=1, max_size=253),
)


def split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({cut % (len(data) + 1) for cut in cuts})
    bounds = [0, *points, len(data)]
    return [data[start:end] for start, end in pairwise(bounds)]


def drain(decoder: MbapDecoder) -> list[MbapFrame]:
    out: list[MbapFrame] = []
    while (frame := decoder.next_frame()) is not None:
        out.append(frame)
    return out


@settings(max_examples=300, deadline=None)
@given(frames)
def test_round_trip(frame: MbapFrame) -> None:
    adu = encode_mbap(*frame)
    assert len(adu) == 7 + len(frame.pdu)
    decoder = MbapDecoder()
    decoder.feed(adu)
    assert decoder.next_frame() == frame
    assert decoder.next_frame() is None
    assert decoder.buffered == 0


@settings(max_examples=150, deadline=None)
@given(st.lists(frames, max_size=8), st.lists(st.integers(min_value=0), max_size=30))
def test_any_chunking_gives_the_same_frames(sent: list[MbapFrame], cuts: list[int]) -> None:
    stream = b"".join(encode_mbap(*frame) for frame in sent)
    decoder = MbapDecoder()
    received: list[MbapFrame] = []
    for chunk in split(stream, cuts):
        decoder.feed(chunk)
        received += drain(decoder)
        assert decoder.buffered <= PARTIAL_LIMIT
    assert received == sent
    assert decoder.buffered == 0


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=300), max_size=8))
def test_arbitrary_bytes_fail_only_with_framing_error(chunks: list[bytes]) -> None:
    decoder = MbapDecoder()
    for chunk in chunks:
        decoder.feed(chunk)
        try:
            for frame in drain(decoder):
                assert 0 <= frame.transaction_id <= 0xFFFF
                assert 1 <= len(frame.pdu) <= 253
        except FramingError as error:
            assert error.kind in ("bad_protocol_id", "bad_length")
            try:
                decoder.feed(b"\x00")
            except FramingError as again:
                assert again is error
            else:
                raise AssertionError("decoder took input after a framing error") from None
            return
        assert decoder.buffered <= PARTIAL_LIMIT


@settings(max_examples=150, deadline=None)
@given(st.lists(frames, min_size=1, max_size=5), st.binary(min_size=7, max_size=40))
def test_frames_before_garbage_are_delivered(sent: list[MbapFrame], garbage: bytes) -> None:
    stream = b"".join(encode_mbap(*frame) for frame in sent)
    decoder = MbapDecoder()
    decoder.feed(stream + garbage)
    for frame in sent:
        assert decoder.next_frame() == frame
    assert decoder.buffered == len(garbage)
