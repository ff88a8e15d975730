"""MBAP codec: the vendor documents' frames, every framing error, chunking, bounds."""

from __future__ import annotations

import pytest

from gateway.core.errors import FramingError, ProtocolError
from gateway.core.mbap import MAX_ADU, MbapDecoder, MbapFrame, encode_mbap
from tests.helpers import h


def drain(decoder: MbapDecoder) -> list[MbapFrame]:
    frames: list[MbapFrame] = []
    while (frame := decoder.next_frame()) is not None:
        frames.append(frame)
    return frames


def decode_all(data: bytes) -> list[MbapFrame]:
    decoder = MbapDecoder()
    decoder.feed(data)
    frames = drain(decoder)
    assert decoder.buffered == 0
    return frames


# (ADU as printed, transaction id, unit id, PDU, source)
REFERENCE_ADUS: list[tuple[str, int, int, str, str]] = [
    # 000 5.3.1 request, printed "0 0 0 5 00 00 00 0 6 01 03 00 00 00 0A".
    ("00 05 0000 0006 01 03 0000 000A", 0x0005, 0x01, "03 0000 000A", "000 5.3.1 request"),
    # 000 5.3.1 response: length 0x17 = 23, 10 registers 0, 5, 10, 15, 0 x 6 (per its table).
    (
        "00 05 0000 0017 01 03 14 0000 0005 000A 000F 0000 0000 0000 0000 0000 0000",
        0x0005,
        0x01,
        "03 14 0000 0005 000A 000F 0000 0000 0000 0000 0000 0000",
        "000 5.3.1 response",
    ),
    # 003 section 2.4: transaction id 0x1501, unit 0xFF, read 1 register at 5.
    ("15 01 0000 0006 FF 03 0005 0001", 0x1501, 0xFF, "03 0005 0001", "003 2.4 request"),
    ("00 00 00 00 00 06 01 03 00 00 00 01", 0, 1, "03 0000 0001", "003 3.1.1 request"),
    ("00 00 00 00 00 05 01 03 02 00 29", 0, 1, "03 02 0029", "003 3.1.1 response"),
    ("00 00 00 00 00 06 01 03 00 01 00 15", 0, 1, "03 0001 0015", "003 3.1.2 request"),
    ("00 00 00 00 00 06 01 03 00 82 00 01", 0, 1, "03 0082 0001", "003 3.1.3 request"),
    ("00 00 00 00 00 05 01 03 02 00 02", 0, 1, "03 02 0002", "003 3.1.3 response"),
    ("00 00 00 00 00 06 01 03 00 83 00 04", 0, 1, "03 0083 0004", "003 3.1.3 example 1"),
    ("00 00 00 00 00 06 01 03 00 85 00 04", 0, 1, "03 0085 0004", "003 3.1.3 example 2"),
]


@pytest.mark.parametrize(("adu", "tid", "unit", "pdu", "source"), REFERENCE_ADUS)
def test_reference_adus_decode(adu: str, tid: int, unit: int, pdu: str, source: str) -> None:
    assert decode_all(h(adu)) == [MbapFrame(tid, unit, h(pdu))], source


@pytest.mark.parametrize(("adu", "tid", "unit", "pdu", "source"), REFERENCE_ADUS)
def test_reference_adus_encode(adu: str, tid: int, unit: int, pdu: str, source: str) -> None:
    assert encode_mbap(tid, unit, h(pdu)) == h(adu), source


def test_000_printed_response_is_one_byte_short_and_waits() -> None:
    # The manual prints 19 data bytes although byte count 0x14 and length 0x17 say 20.
    printed = h(
        "00 05 00 00 00 17 01 03 14 00 00 00 05 00 0A 00 0F 00 00 00 00 00 00 00 00 00 00 00"
    )
    decoder = MbapDecoder()
    decoder.feed(printed)
    assert decoder.next_frame() is None
    assert decoder.buffered == 28
    decoder.feed(b"\x00")
    frame = decoder.next_frame()
    assert frame is not None
    assert frame.transaction_id == 5
    assert len(frame.pdu) == 22


def test_003_counter_list_response_is_printed_short_and_waits() -> None:
    # "00 00 00 00 00 0b 01 03 08 00 00 00 00 00 00 01": length 11 needs 8 data bytes, 7 printed.
    decoder = MbapDecoder()
    decoder.feed(h("00 00 00 00 00 0b 01 03 08 00 00 00 00 00 00 01"))
    assert decoder.next_frame() is None
    assert decoder.buffered == 16


def test_003_version_response_is_split_by_its_length_field() -> None:
    # The version response's byte count (0x2a = 42) disagrees with its 41 printed bytes;
    # MBAP framing goes by the length field (0x2c = 44) and passes the PDU on untouched.
    version = b"AM8-QC-RXE-7.8.02-bate7_FAKE_TGF_ENCODER\x00"
    adu = h("00 00 00 00 00 2c 01 03 2a") + version
    assert decode_all(adu) == [MbapFrame(0, 1, b"\x03\x2a" + version)]


# ---- framing errors -------------------------------------------------------------------


@pytest.mark.parametrize("protocol_id", [0x0001, 0x0100, 0x00FF, 0xFFFF])
def test_nonzero_protocol_id_is_a_framing_error(protocol_id: int) -> None:
    adu = bytearray(encode_mbap(1, 1, h("03 0000 0001")))
    adu[2:4] = protocol_id.to_bytes(2, "big")
    decoder = MbapDecoder()
    decoder.feed(adu)
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "bad_protocol_id"
    assert isinstance(caught.value, ProtocolError)


@pytest.mark.parametrize("length", [0, 1, 255, 256, 0x0100, 0x7FFF, 0xFFFF])
def test_length_outside_2_to_254_is_a_framing_error(length: int) -> None:
    header = h("00 01 00 00") + length.to_bytes(2, "big") + b"\x01"
    decoder = MbapDecoder()
    decoder.feed(header)  # the header alone is enough to know the stream is broken
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "bad_length"


@pytest.mark.parametrize("length", [2, 254])
def test_length_boundaries_are_accepted(length: int) -> None:
    pdu = bytes([0x41]) + bytes(length - 2)
    adu = encode_mbap(0x1234, 7, pdu)
    assert len(adu) == 6 + length
    assert decode_all(adu) == [MbapFrame(0x1234, 7, pdu)]


def test_largest_adu_is_260_bytes() -> None:
    adu = encode_mbap(1, 1, bytes(253))
    assert len(adu) == MAX_ADU == 260
    assert decode_all(adu)[0].pdu == bytes(253)


def test_protocol_id_is_checked_before_length() -> None:
    decoder = MbapDecoder()
    decoder.feed(h("00 01 00 01 00 00 01"))
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "bad_protocol_id"


def test_six_header_bytes_are_not_judged_yet() -> None:
    decoder = MbapDecoder()
    decoder.feed(h("00 01 00 07 FF FF"))  # bad protocol id and length, but no unit id yet
    assert decoder.next_frame() is None
    assert decoder.buffered == 6
    decoder.feed(b"\x01")
    with pytest.raises(FramingError):
        decoder.next_frame()


def test_decoder_refuses_everything_after_a_failure() -> None:
    decoder = MbapDecoder()
    decoder.feed(h("00 01 00 00 00 00 01"))
    with pytest.raises(FramingError) as first:
        decoder.next_frame()
    with pytest.raises(FramingError) as again:
        decoder.next_frame()
    with pytest.raises(FramingError) as fed:
        decoder.feed(encode_mbap(2, 1, h("03 0000 0001")))
    assert again.value is first.value
    assert fed.value is first.value
    assert first.value.kind == "bad_length"


def test_frames_before_a_broken_header_are_still_delivered() -> None:
    good = [encode_mbap(tid, 1, h("03 0000 0001")) for tid in (1, 2)]
    decoder = MbapDecoder()
    decoder.feed(good[0] + good[1] + h("00 03 00 05 00 06 01 03 00 00 00 01"))
    assert decoder.next_frame() == MbapFrame(1, 1, h("03 0000 0001"))
    assert decoder.next_frame() == MbapFrame(2, 1, h("03 0000 0001"))
    with pytest.raises(FramingError) as caught:
        decoder.next_frame()
    assert caught.value.kind == "bad_protocol_id"


# ---- chunking ----------------------------------------------------------------------


STREAM_FRAMES = [
    MbapFrame(0x0005, 0x01, h("03 0000 000A")),
    MbapFrame(0x1501, 0xFF, h("03 0005 0001")),
    MbapFrame(0xFFFF, 0x00, h("10 0002 0003 06 1122 3344 5566")),
    MbapFrame(0x0000, 0x11, h("2B 0E 01 00")),
    MbapFrame(0x8001, 0xF7, h("41")),
]
STREAM = b"".join(encode_mbap(*frame) for frame in STREAM_FRAMES)


@pytest.mark.parametrize("split", range(len(STREAM) + 1))
def test_stream_split_at_every_byte_boundary(split: int) -> None:
    decoder = MbapDecoder()
    decoder.feed(STREAM[:split])
    frames = drain(decoder)
    decoder.feed(STREAM[split:])
    frames += drain(decoder)
    assert frames == STREAM_FRAMES
    assert decoder.buffered == 0


def test_stream_fed_one_byte_at_a_time() -> None:
    decoder = MbapDecoder()
    frames: list[MbapFrame] = []
    ends: list[int] = []
    for index in range(len(STREAM)):
        decoder.feed(STREAM[index : index + 1])
        while (frame := decoder.next_frame()) is not None:
            frames.append(frame)
            ends.append(index + 1)
    assert frames == STREAM_FRAMES
    # Each frame comes out the moment its last byte arrives, not later.
    expected_ends: list[int] = []
    offset = 0
    for frame in STREAM_FRAMES:
        offset += 7 + len(frame.pdu)
        expected_ends.append(offset)
    assert ends == expected_ends


def test_many_frames_in_one_chunk_come_out_in_order() -> None:
    frames = [MbapFrame(tid, tid % 248, bytes([3, 0, tid % 256, 0, 1])) for tid in range(500)]
    assert decode_all(b"".join(encode_mbap(*frame) for frame in frames)) == frames


def test_memoryview_and_bytearray_input() -> None:
    decoder = MbapDecoder()
    decoder.feed(memoryview(STREAM)[:10])
    decoder.feed(bytearray(STREAM[10:]))
    assert drain(decoder) == STREAM_FRAMES


def test_buffered_counts_unreturned_bytes() -> None:
    adu = encode_mbap(9, 1, h("03 0000 0001"))
    decoder = MbapDecoder()
    assert decoder.buffered == 0
    decoder.feed(adu + adu[:3])
    assert decoder.buffered == 15
    assert decoder.next_frame() == MbapFrame(9, 1, h("03 0000 0001"))
    assert decoder.buffered == 3
    assert decoder.next_frame() is None
    assert decoder.buffered == 3


# ---- encoder ----------------------------------------------------------------------


def test_encode_puts_fields_big_endian() -> None:
    assert encode_mbap(0xABCD, 0x5A, h("83 02")) == h("AB CD 00 00 00 03 5A 83 02")


def test_encode_length_of_longest_pdu() -> None:
    adu = encode_mbap(1, 2, bytes(range(253)))
    assert adu[4:6] == h("00 FE")
    assert adu[6] == 2
    assert adu[7:] == bytes(range(253))
