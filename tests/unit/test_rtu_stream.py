"""RTU requests split out of a TCP stream: by predicted length and CRC, whatever the chunking."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.crc import append_crc
from gateway.core.errors import FramingError
from gateway.core.mbap import MbapFrame
from gateway.core.rtu_stream import RtuStreamDecoder, encode_rtu_reply, heard_request
from tests.helpers import h

#: Requests of every length rule: fixed, byte count at 6, at 2, at 10, MEI, diagnostics.
REQUESTS = [
    h("01 03 0000 000A"), h("11 01 0013 0013"), h("01 10 0001 0002 04 000A 0102"),
    h("01 0F 0013 000A 02 CD01"), h("01 14 0E 06 0004 0001 0002 06 0003 0009 0002"),
    h("01 17 0003 0006 000E 0003 06 00FF 00FF 00FF"), h("01 2B 0E 01 00"), h("01 08 0000 A537"),
    h("01 07"), h("01 16 0004 00F2 0025"), h("01 18 04DE"), h("00 06 0001 0003"),
]  # fmt: skip


def frames_of(decoder: RtuStreamDecoder) -> list[MbapFrame]:
    out = []
    while (frame := decoder.next_frame()) is not None:
        out.append(frame)
    return out


def test_the_specification_example_and_a_reply() -> None:
    decoder = RtuStreamDecoder()
    decoder.feed(h("11 03 006B 0003 7687"))  # Modbus over Serial Line, read holding registers
    assert frames_of(decoder) == [MbapFrame(0, 0x11, h("03 006B 0003"))]
    assert encode_rtu_reply(0x11, h("03 06 AE41 5652 4340")) == h("11 03 06 AE41 5652 4340 49AD")


@given(st.data())
def test_any_chunking_gives_the_same_frames(data: st.DataObject) -> None:
    picked = data.draw(st.lists(st.sampled_from(REQUESTS), min_size=1, max_size=8))
    stream = b"".join(append_crc(request) for request in picked)
    cuts = sorted(data.draw(st.sets(st.integers(1, len(stream) - 1), max_size=len(stream) // 2)))
    decoder = RtuStreamDecoder()
    frames: list[MbapFrame] = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        decoder.feed(stream[start:end])
        frames.extend(frames_of(decoder))
    assert [(f.unit_id, f.pdu) for f in frames] == [(r[0], r[1:]) for r in picked]
    assert [f.transaction_id for f in frames] == list(range(len(picked)))
    assert decoder.buffered == 0


def test_a_bad_crc_fails_the_stream_for_good() -> None:
    decoder = RtuStreamDecoder()
    decoder.feed(h("11 03 006B 0003 7688"))
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "bad_crc"
    with pytest.raises(FramingError):
        decoder.feed(append_crc(h("11 03 006B 0003")))


def test_an_unknown_function_ends_on_silence_only() -> None:
    decoder = RtuStreamDecoder()
    decoder.feed(append_crc(h("01 41 AA BB"))[:3])
    assert decoder.awaiting_silence and decoder.next_frame() is None
    decoder.feed(append_crc(h("01 41 AA BB"))[3:])
    assert decoder.next_frame() is None  # no silence yet
    decoder.silence()
    assert decoder.next_frame() == MbapFrame(0, 1, h("41 AA BB"))
    assert not decoder.awaiting_silence


def test_a_silence_seen_while_a_request_waited_ends_the_next_one_too() -> None:
    decoder = RtuStreamDecoder()
    decoder.feed(append_crc(h("01 03 0000 0001")) + append_crc(h("01 41 AA")))
    decoder.silence()  # came while the master's first request was still being answered
    assert decoder.next_frame() == MbapFrame(0, 1, h("03 0000 0001"))
    assert decoder.next_frame() == MbapFrame(1, 1, h("41 AA"))


def test_an_endless_request_of_unknown_length_is_refused() -> None:
    decoder = RtuStreamDecoder()
    decoder.feed(h("01 41") + bytes(255))
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "too_long"


def test_a_heard_frame_is_a_request_damaged_or_another_slaves() -> None:
    """What a serial-slave listener makes of a frame between two silences."""
    request = bytes.fromhex("010300000001")
    frame = request + bytes.fromhex("840a")
    assert heard_request(frame) == (1, bytes.fromhex("0300000001"))
    assert isinstance(heard_request(frame[:-1] + b"\x00"), str)  # bad CRC
    assert isinstance(heard_request(b"\x01\x03"), str)  # too short
    answer = bytes.fromhex("01 03 02 00 2a")
    assert heard_request(append_crc(answer)) is None  # an answer on the bus: not a request
