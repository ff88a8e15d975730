"""RTU properties: CRC residue, encode/decode round trip under any chunking, the answer found
behind noise, bounded decoder, length predictors and request validation that never fail
outside the ProtocolError family."""

from __future__ import annotations

from itertools import pairwise
from typing import NamedTuple

from hypothesis import assume, given, settings
from hypothesis import strategies as st

from gateway.core.crc import append_crc, check_crc, crc16, crc16_bytes
from gateway.core.errors import ModbusError, ResponseError
from gateway.core.pdu import validate_request
from gateway.core.rtu import (
    MAX_NOISE,
    MAX_RTU_FRAME,
    NEED_MORE,
    RtuFrame,
    RtuResponseDecoder,
    encode_rtu,
    request_length,
    response_length,
)
from tests.helpers import decode_as_the_core_does

SETTINGS = settings(max_examples=200, deadline=None)


class Exchange(NamedTuple):
    request: bytes
    response: bytes


def u16(value: int) -> bytes:
    return value.to_bytes(2, "big")


def split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({cut % (len(data) + 1) for cut in cuts})
    return [data[start:end] for start, end in pairwise([0, *points, len(data)])]


@st.composite
def exchanges(draw: st.DrawFn) -> Exchange:
    """A request and a well-formed response whose length the response alone predicts."""
    kind = draw(
        st.sampled_from(
            [
                "bits",
                "registers",
                "echo",
                "write_multiple",
                "fixed",
                "byte_count",
                "fifo",
                "read_write",
                "diagnostics",
                "device_id",
                "exception",
            ]
        )
    )
    address = draw(st.integers(0, 0xFFFF))
    if kind == "bits":
        function = draw(st.sampled_from([0x01, 0x02]))
        quantity = draw(st.integers(1, 2000))
        data = draw(st.binary(min_size=(quantity + 7) // 8, max_size=(quantity + 7) // 8))
        request = bytes((function,)) + u16(address) + u16(quantity)
        return Exchange(request, bytes((function, len(data))) + data)
    if kind == "registers":
        function = draw(st.sampled_from([0x03, 0x04]))
        quantity = draw(st.integers(1, 125))
        data = draw(st.binary(min_size=2 * quantity, max_size=2 * quantity))
        request = bytes((function,)) + u16(address) + u16(quantity)
        return Exchange(request, bytes((function, len(data))) + data)
    if kind == "echo":
        function = draw(st.sampled_from([0x05, 0x06, 0x16]))
        size = 6 if function == 0x16 else 4
        request = bytes((function,)) + draw(st.binary(min_size=size, max_size=size))
        return Exchange(request, request)
    if kind == "write_multiple":
        function = draw(st.sampled_from([0x0F, 0x10]))
        quantity = draw(st.integers(1, 123))
        count = (quantity + 7) // 8 if function == 0x0F else 2 * quantity
        head = bytes((function,)) + u16(address) + u16(quantity)
        return Exchange(head + bytes((count,)) + bytes(count), head)
    if kind == "fixed":
        function = draw(st.sampled_from([0x07, 0x0B]))
        size = 1 if function == 0x07 else 4
        return Exchange(
            bytes((function,)), bytes((function,)) + draw(st.binary(min_size=size, max_size=size))
        )
    if kind == "byte_count":
        function = draw(st.sampled_from([0x0C, 0x11, 0x14]))
        data = draw(st.binary(max_size=251))
        return Exchange(bytes((function,)), bytes((function, len(data))) + data)
    if kind == "fifo":
        count = draw(st.integers(0, 31))
        values = draw(st.binary(min_size=2 * count, max_size=2 * count))
        response = bytes((0x18,)) + u16(2 + 2 * count) + u16(count) + values
        return Exchange(bytes((0x18,)) + u16(address), response)
    if kind == "read_write":
        quantity = draw(st.integers(1, 125))
        data = draw(st.binary(min_size=2 * quantity, max_size=2 * quantity))
        request = bytes((0x17,)) + u16(address) + u16(quantity) + u16(0) + u16(1) + b"\x02\x00\x00"
        return Exchange(request, bytes((0x17, len(data))) + data)
    if kind == "diagnostics":
        request = bytes((0x08,)) + draw(st.binary(min_size=2, max_size=60))
        return Exchange(request, request)
    if kind == "device_id":
        items = draw(st.lists(st.binary(max_size=60), max_size=4))
        objects = b"".join(bytes((index, len(item))) + item for index, item in enumerate(items))
        head = bytes((0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, len(items)))
        return Exchange(bytes((0x2B, 0x0E, 0x01, 0x00)), head + objects)
    function = draw(st.sampled_from([0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x41]))
    return Exchange(bytes((function,)), bytes((function | 0x80, draw(st.integers(1, 0x0B)))))


@SETTINGS
@given(st.binary(max_size=300))
def test_crc_of_frame_with_its_crc_is_zero(data: bytes) -> None:
    assert crc16(data + crc16_bytes(data)) == 0
    assert append_crc(data) == data + crc16_bytes(data)
    assert check_crc(append_crc(data)) == (len(data) >= 1)


@SETTINGS
@given(st.binary(min_size=1, max_size=254), st.data())
def test_crc_detects_any_single_bit_error(data: bytes, choice: st.DataObject) -> None:
    frame = bytearray(append_crc(data))
    bit = choice.draw(st.integers(0, 8 * len(frame) - 1))
    frame[bit // 8] ^= 1 << (bit % 8)
    assert not check_crc(frame)


@SETTINGS
@given(exchanges(), st.integers(1, 247), st.lists(st.integers(min_value=0), max_size=12))
def test_round_trip_under_any_chunking(exchange: Exchange, unit: int, cuts: list[int]) -> None:
    frame = encode_rtu(unit, exchange.response)
    assert len(frame) <= MAX_RTU_FRAME
    assert response_length(exchange.request, frame) == len(frame)
    decoder = RtuResponseDecoder(unit, exchange.request)
    chunks = [chunk for chunk in split(frame, cuts) if chunk]
    for chunk in chunks[:-1]:
        assert decoder.feed(chunk) is None
    assert decoder.feed(chunks[-1]) == RtuFrame(unit, exchange.response)
    assert not decoder.waits_for_silence


@st.composite
def noise_in_front(draw: st.DrawFn) -> tuple[Exchange, int, bytes]:
    """An exchange, its unit, and up to ``MAX_NOISE`` bytes of noise without that unit's
    address (a transceiver turning around puts such bytes before the answer)."""
    exchange = draw(exchanges())
    unit = draw(st.integers(1, 247))
    byte = st.integers(0, 255).filter(lambda value: value != unit)
    noise = bytes(draw(st.lists(byte, min_size=1, max_size=MAX_NOISE)))
    assume(not _reads_as_a_frame(noise, encode_rtu(unit, exchange.response)))
    return exchange, unit, noise


def _reads_as_a_frame(noise: bytes, answer: bytes) -> bool:
    """True when bytes of ``noise`` and the first bytes of ``answer`` make an intact frame.

    About one noise in 65,536 does: its CRC happens to come out right. That frame (of
    another unit) is taken for what it says it is, the answer's head goes with it, and the
    request ends in a timeout: no wrong answer, but no answer either, so these tests, which
    promise the answer, leave such noise out.
    """
    stream = noise + answer
    return any(
        check_crc(stream[start:end])
        for start in range(len(noise))
        for end in range(len(noise) + 1, len(stream) + 1)
        if end - start >= 4
    )


@SETTINGS
@given(noise_in_front())
def test_the_answer_behind_noise_in_the_same_read_is_found(
    case: tuple[Exchange, int, bytes],
) -> None:
    exchange, unit, noise = case
    decoder = RtuResponseDecoder(unit, exchange.request)
    happened = decode_as_the_core_does(decoder, [noise + encode_rtu(unit, exchange.response)])
    # Noise that happens to be a valid frame of another unit is skipped as that.
    assert happened[0] in ("noise", "unexpected_unit"), happened
    assert happened[1:] == [RtuFrame(unit, exchange.response)]


@SETTINGS
@given(noise_in_front(), st.lists(st.integers(min_value=0), max_size=12))
def test_the_answer_behind_noise_is_found_under_any_chunking(
    case: tuple[Exchange, int, bytes], cuts: list[int]
) -> None:
    """Noise decided on its own (before the answer's bytes came) fails as garbage; the
    answer behind it is still found, and nothing else is ever taken for it."""
    exchange, unit, noise = case
    decoder = RtuResponseDecoder(unit, exchange.request)
    chunks = [chunk for chunk in split(noise + encode_rtu(unit, exchange.response), cuts) if chunk]
    happened = decode_as_the_core_does(decoder, chunks)
    assert happened[-1] == RtuFrame(unit, exchange.response)
    skipped = {"noise", "unexpected_unit", "crc", "oversize", "short_frame"}
    assert set(happened[:-1]) <= skipped, happened


@SETTINGS
@given(
    st.integers(0, 255),
    st.binary(min_size=1, max_size=253),
    st.lists(st.binary(max_size=120), max_size=6),
    st.booleans(),
)
def test_arbitrary_bytes_never_crash_nor_overfill_the_decoder(
    unit: int, request: bytes, chunks: list[bytes], silence: bool
) -> None:
    decoder = RtuResponseDecoder(unit, request)
    for chunk in chunks:
        try:
            frame = decoder.feed(chunk)
        except ResponseError:
            assert decoder.buffered <= MAX_RTU_FRAME
            decoder.reset()
            continue
        assert decoder.buffered <= MAX_RTU_FRAME
        if frame is not None:
            assert frame.unit == unit
            assert frame.pdu[0] & 0x7F == request[0]
            decoder.reset()
    if silence:
        try:
            frame = decoder.end_of_frame()
        except ResponseError:
            return
        assert frame.unit == unit
        assert check_crc(encode_rtu(frame.unit, frame.pdu))


@SETTINGS
@given(st.binary(max_size=253), st.binary(max_size=300))
def test_length_predictors_are_total(request: bytes, prefix: bytes) -> None:
    for predicted in (response_length(request, prefix), request_length(prefix)):
        assert predicted is None or predicted == NEED_MORE or predicted >= 4


@SETTINGS
@given(st.binary(max_size=300))
def test_validate_request_fails_only_with_modbus_error(pdu: bytes) -> None:
    try:
        validate_request(pdu)
    except ModbusError as error:
        assert error.code in (0x01, 0x02, 0x03)


@st.composite
def valid_requests(draw: st.DrawFn) -> bytes:
    """Requests within every limit of the specification."""
    function = draw(st.sampled_from([0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x17]))
    if function in (0x01, 0x02, 0x0F):
        quantity = draw(st.integers(1, 2000 if function != 0x0F else 1968))
    elif function == 0x10:
        quantity = draw(st.integers(1, 123))
    else:
        quantity = draw(st.integers(1, 125))
    address = draw(st.integers(0, 0x10000 - quantity))
    head = bytes((function,)) + u16(address)
    if function == 0x05:
        return head + draw(st.sampled_from([b"\xff\x00", b"\x00\x00"]))
    if function == 0x06:
        return head + draw(st.binary(min_size=2, max_size=2))
    head += u16(quantity)
    if function == 0x0F:
        count = (quantity + 7) // 8
        return head + bytes((count,)) + draw(st.binary(min_size=count, max_size=count))
    if function == 0x10:
        return (
            head
            + bytes((2 * quantity,))
            + draw(st.binary(min_size=2 * quantity, max_size=2 * quantity))
        )
    if function == 0x17:
        writes = draw(st.integers(1, 121))
        write_address = draw(st.integers(0, 0x10000 - writes))
        return head + u16(write_address) + u16(writes) + bytes((2 * writes,)) + bytes(2 * writes)
    return head


@SETTINGS
@given(valid_requests(), st.integers(0, 247))
def test_valid_requests_pass_and_their_length_is_predicted(pdu: bytes, unit: int) -> None:
    validate_request(pdu)
    frame = encode_rtu(unit, pdu)
    assert len(frame) <= MAX_RTU_FRAME
    assert request_length(frame) == len(frame)
    assert request_length(frame[:11]) == len(frame)
