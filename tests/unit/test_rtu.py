"""RTU codec: length prediction for every function code, and the response decoder's checks.

PDU examples come from the vendor documents (000, 001, 004) and, for the function codes
they do not cover, from the worked examples of the Modbus Application Protocol v1.1b3.
"""

from __future__ import annotations

import pytest

from gateway.core.crc import append_crc
from gateway.core.errors import ProtocolError, ResponseError
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
from tests.helpers import decode_as_the_core_does, h

DEVICE_ID_OBJECTS = [
    # 002 (ZL-69X) example: objects 0, 1, 2 of lengths 0x16, 0x0A, 0x05.
    (0x00, b"Company identification"),
    (0x01, b"ZL-690 v35"),
    (0x02, b"V2.11"),
]
DEVICE_ID_RESPONSE = h("2B 0E 01 01 00 00 03") + b"".join(
    bytes((obj, len(value))) + value for obj, value in DEVICE_ID_OBJECTS
)

# (function code, request PDU, response PDU)
EXCHANGES: list[tuple[int, str, bytes]] = [
    (0x01, "01 0013 0013", h("01 03 CD 6B 05")),
    (0x02, "02 0006 0012", h("02 03 11 22 03")),  # 004
    (0x03, "03 0002 0003", h("03 06 1122 3344 5566")),  # 004
    (0x03, "03 0000 000A", h("03 14 0000 0002 0004 0006 0008 000A") + bytes(8)),  # 000 5.3.2
    (0x03, "03 0003 0003", h("03 06 0000 00B7 0000")),  # 001
    (0x04, "04 0006 0002", h("04 04 1122 3344")),  # 004
    (0x05, "05 0012 FF00", h("05 0012 FF00")),  # 004
    (0x06, "06 0007 1234", h("06 0007 1234")),  # 004
    (0x07, "07", h("07 6D")),
    (0x08, "08 0000 A537", h("08 0000 A537")),
    (0x0B, "0B", h("0B FFFF 0108")),
    (0x0C, "0C", h("0C 08 0000 0108 0121 2000")),
    (0x0F, "0F 0006 0009 02 11 01", h("0F 0006 0009")),  # 004
    (0x10, "10 0002 0003 06 1122 3344 5566", h("10 0002 0003")),  # 004
    (0x11, "11", h("11 05 01 FF 41 42 43")),
    (
        0x14,
        "14 0E 06 0004 0001 0002 06 0003 0009 0002",
        h("14 0C 05 06 0DFE 0020 05 06 33CD 0040"),
    ),
    (
        0x15,
        "15 0D 06 0004 0007 0003 06AF 04BE 100D",
        h("15 0D 06 0004 0007 0003 06AF 04BE 100D"),
    ),
    (0x16, "16 0004 00F2 0025", h("16 0004 00F2 0025")),
    (
        0x17,
        "17 0003 0006 000E 0003 06 00FF 00FF 00FF",
        h("17 0C 00FE 0ACD 0001 0003 000D 00FF"),
    ),
    (0x18, "18 04DE", h("18 0006 0002 01B8 1284")),
    (0x2B, "2B 0E 01 00", DEVICE_ID_RESPONSE),
]

IDS = [f"fc{fc:02d}-{index}" for index, (fc, _, _) in enumerate(EXCHANGES)]


# ---- response_length ------------------------------------------------------------------


@pytest.mark.parametrize(("function", "request_pdu", "response"), EXCHANGES, ids=IDS)
def test_response_length_of_every_function(
    function: int, request_pdu: str, response: bytes
) -> None:
    frame = encode_rtu(0x11, response)
    assert frame[1] == function
    assert response_length(h(request_pdu), frame) == len(frame)


@pytest.mark.parametrize(("function", "request_pdu", "response"), EXCHANGES, ids=IDS)
def test_response_length_is_stable_once_known(
    function: int, request_pdu: str, response: bytes
) -> None:
    """Each prefix says NEED_MORE until the length can be told, then the same final answer."""
    frame = encode_rtu(0x11, response)
    answers = [response_length(h(request_pdu), frame[:end]) for end in range(len(frame) + 1)]
    known = [answer for answer in answers if answer != NEED_MORE]
    assert known and all(answer == len(frame) for answer in known)
    first = answers.index(len(frame))
    assert all(answer == NEED_MORE for answer in answers[:first])
    assert first <= len(frame)


@pytest.mark.parametrize(
    ("prefix", "expected"),
    [
        ("", NEED_MORE),
        ("01", NEED_MORE),
        ("01 03", NEED_MORE),  # byte count not yet seen
        ("01 03 06", 11),
        ("01 01 00", 5),  # a zero byte count is still a length
        ("01 03 FB", 256),
        ("01 03 FF", 260),  # beyond an RTU frame: the decoder calls it oversize
        ("01 05", 8),
        ("01 07", 5),
        ("01 0B", 8),
        ("01 16", 10),
        ("01 18 00", NEED_MORE),
        ("01 18 00 06", 12),
        ("01 2B", NEED_MORE),
        ("01 2B 0E 01 01 00", NEED_MORE),
        ("01 2B 0E 01 01 00 00 00", 10),  # no objects
        ("01 2B 0E 01 01 00 00 01 00", NEED_MORE),  # object header incomplete
        ("01 2B 0E 01 01 00 00 01 00 03", 15),
    ],
)
def test_response_length_from_prefixes(prefix: str, expected: int) -> None:
    assert response_length(h("03 0000 0001"), h(prefix)) == expected


@pytest.mark.parametrize("function", [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x0F, 0x10, 0x2B])
@pytest.mark.parametrize("code", [0x01, 0x02, 0x03, 0x04, 0x0B])
def test_exception_response_is_five_bytes(function: int, code: int) -> None:
    frame = encode_rtu(1, bytes((function | 0x80, code)))
    assert len(frame) == 5
    assert response_length(bytes((function,)), frame[:2]) == 5


@pytest.mark.parametrize("function", [0x09, 0x0A, 0x0D, 0x0E, 0x13, 0x19, 0x29, 0x41, 0x64, 0x7F])
def test_unknown_function_codes_end_on_silence(function: int) -> None:
    assert response_length(bytes((function,)), bytes((1, function, 0, 0, 0, 0))) is None


def test_device_id_with_another_mei_type_ends_on_silence() -> None:
    assert response_length(h("2B 0D 00"), h("01 2B 0D 00 00 00 00 00")) is None


@pytest.mark.parametrize("function", [0x08, 0x15])
def test_echo_response_to_another_request_ends_on_silence(function: int) -> None:
    assert response_length(h("03 0000 0001"), bytes((1, function, 0, 0))) is None
    assert response_length(b"", bytes((1, function, 0, 0))) is None


def test_diagnostics_echo_follows_request_length() -> None:
    assert response_length(h("08 0000 A537 1234"), h("01 08")) == 10


def test_device_id_objects_past_a_frame_are_oversize() -> None:
    prefix = h("01 2B 0E 01 01 FF 00 03 00 FF 01 FF")
    answer = response_length(h("2B 0E 01 00"), prefix)
    assert answer is not None
    assert answer > MAX_RTU_FRAME


# ---- request_length -------------------------------------------------------------------


@pytest.mark.parametrize(
    "request_pdu",
    [request for _, request, _ in EXCHANGES if not request.startswith("08")]
    + ["01 0000 07D0", "04 FFFF 0001", "2B 0E 04 80"],
)
def test_request_length_of_every_request(request_pdu: str) -> None:
    frame = encode_rtu(0x22, h(request_pdu))
    assert request_length(frame) == len(frame)
    assert request_length(frame[:11]) == len(frame)


@pytest.mark.parametrize(
    ("prefix", "expected"),
    [
        ("", NEED_MORE),
        ("01", NEED_MORE),
        ("01 01", 8),
        ("01 02", 8),
        ("01 03", 8),
        ("01 04", 8),
        ("01 05", 8),
        ("01 06", 8),
        ("01 07", 4),
        ("01 0B", 4),
        ("01 0C", 4),
        ("01 11", 4),
        ("01 0F 00 00 00 09", NEED_MORE),
        ("01 0F 00 00 00 09 02", 11),
        ("01 10 00 00 00 7B F6", 255),
        ("01 14", NEED_MORE),
        ("01 14 07", 12),
        ("01 15 FB", 256),
        ("01 16", 10),
        ("01 17 00 00 00 01 00 00 00 01", NEED_MORE),
        ("01 17 00 00 00 01 00 00 00 01 02", 15),
        ("01 18", 6),
        ("01 2B", NEED_MORE),
        ("01 2B 0E", 7),
    ],
)
def test_request_length_from_prefixes(prefix: str, expected: int) -> None:
    assert request_length(h(prefix)) == expected


@pytest.mark.parametrize("prefix", ["01 08 00 00", "01 2B 0D", "01 41", "01 09", "01 83 02"])
def test_request_length_unknown(prefix: str) -> None:
    assert request_length(h(prefix)) is None


# ---- encode_rtu -----------------------------------------------------------------------


def test_encode_rtu_reference_frames() -> None:
    assert encode_rtu(1, h("03 0000 000A")) == h("01 03 00 00 00 0A C5 CD")  # 000
    assert encode_rtu(1, h("03 0003 0003")) == h("01 03 00 03 00 03 F5 CB")  # 001
    assert encode_rtu(1, h("03 06 0000 00B7 0000")) == h("01 03 06 00 00 00 B7 00 00 91 53")


# ---- RtuResponseDecoder ---------------------------------------------------------------

RESPONSE_000 = h("01 03 14 0000 0002 0004 0006 0008 000A 0000 0000 0000 0000 5B 02")


def test_decoder_accepts_000_response_in_one_chunk() -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 000A"))
    frame = decoder.feed(RESPONSE_000)
    assert frame == RtuFrame(1, RESPONSE_000[1:-2])
    assert frame.pdu[:2] == h("03 14")
    assert not decoder.waits_for_silence


def test_decoder_completes_exactly_at_the_last_byte() -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 000A"))
    for index in range(len(RESPONSE_000) - 1):
        assert decoder.feed(RESPONSE_000[index : index + 1]) is None
        assert decoder.buffered == index + 1
    assert decoder.feed(RESPONSE_000[-1:]) == RtuFrame(1, RESPONSE_000[1:-2])


@pytest.mark.parametrize(("function", "request_pdu", "response"), EXCHANGES, ids=IDS)
def test_decoder_returns_every_function_at_its_predicted_end(
    function: int, request_pdu: str, response: bytes
) -> None:
    frame = encode_rtu(0x11, response)
    decoder = RtuResponseDecoder(0x11, h(request_pdu))
    assert decoder.feed(frame[:-1]) is None
    assert decoder.feed(frame[-1:]) == RtuFrame(0x11, response)
    assert not decoder.waits_for_silence


def test_decoder_accepts_exception_response() -> None:
    decoder = RtuResponseDecoder(0x0A, h("03 0000 007E"))
    frame = encode_rtu(0x0A, h("83 03"))
    assert decoder.feed(frame[:4]) is None
    assert decoder.feed(frame[4:]) == RtuFrame(0x0A, h("83 03"))


def test_decoder_rejects_bad_crc() -> None:
    frame = bytearray(RESPONSE_000)
    frame[10] ^= 0xFF
    decoder = RtuResponseDecoder(1, h("03 0000 000A"))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(frame)
    assert caught.value.kind == "crc"
    assert isinstance(caught.value, ProtocolError)


def test_decoder_rejects_wrong_unit_and_then_takes_the_right_one() -> None:
    decoder = RtuResponseDecoder(2, h("03 0000 0001"))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(encode_rtu(3, h("03 02 1234")))
    assert caught.value.kind == "unexpected_unit"
    decoder.reset()
    assert decoder.buffered == 0
    assert decoder.feed(encode_rtu(2, h("03 02 1234"))) == RtuFrame(2, h("03 02 1234"))


@pytest.mark.parametrize("pdu", ["04 02 1234", "84 02", "06 0000 0001"])
def test_decoder_rejects_wrong_function(pdu: str) -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 0001"))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(encode_rtu(1, h(pdu)))
    assert caught.value.kind == "unexpected_function"


def test_decoder_accepts_the_largest_frame() -> None:
    response = bytes((0x11, 251)) + bytes(range(251))
    frame = encode_rtu(1, response)
    assert len(frame) == MAX_RTU_FRAME
    decoder = RtuResponseDecoder(1, h("11"))
    assert decoder.feed(frame) == RtuFrame(1, response)


def test_decoder_rejects_announced_oversize_at_the_byte_count() -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 007D"))
    assert decoder.feed(h("01 03")) is None
    with pytest.raises(ResponseError) as caught:
        decoder.feed(bytes((252,)))  # 5 + 252 = 257 bytes
    assert caught.value.kind == "oversize"


def test_decoder_rejects_fifo_count_past_a_frame() -> None:
    decoder = RtuResponseDecoder(1, h("18 0000"))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(h("01 18 01 00"))
    assert caught.value.kind == "oversize"


def test_decoder_leaves_trailing_bytes_to_the_caller() -> None:
    decoder = RtuResponseDecoder(1, h("06 0001 0003"))
    frame = decoder.feed(encode_rtu(1, h("06 0001 0003")) + b"\x00\x01")
    assert frame == RtuFrame(1, h("06 0001 0003"))
    assert decoder.leftover == b"\x00\x01"


def test_decoder_keeps_what_follows_a_discarded_frame() -> None:
    request = h("03 0000 0001")
    decoder = RtuResponseDecoder(1, request)
    foreign = encode_rtu(2, h("03 02 0007"))
    answer = encode_rtu(1, h("03 02 002A"))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(foreign + answer)
    assert caught.value.kind == "unexpected_unit"
    leftover = decoder.leftover
    decoder.reset()
    assert decoder.feed(leftover) == RtuFrame(1, h("03 02 002A"))


def test_silence_terminated_frame() -> None:
    response = h("41 01 02 03 04 05")
    frame = encode_rtu(5, response)
    decoder = RtuResponseDecoder(5, h("41 00"))
    assert decoder.feed(frame[:1]) is None
    assert not decoder.waits_for_silence  # one byte cannot tell the function yet
    assert decoder.feed(frame[1:]) is None
    assert decoder.waits_for_silence
    assert decoder.buffered == len(frame)
    assert decoder.end_of_frame() == RtuFrame(5, response)


def test_silence_terminated_frame_with_bad_crc() -> None:
    decoder = RtuResponseDecoder(5, h("41 00"))
    decoder.feed(h("05 41 01 02 03 04"))
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "crc"


def test_silence_terminated_frame_may_fill_but_not_pass_256_bytes() -> None:
    decoder = RtuResponseDecoder(5, h("41"))
    frame = encode_rtu(5, bytes((0x41,)) + bytes(252))
    assert len(frame) == MAX_RTU_FRAME
    assert decoder.feed(frame) is None
    assert decoder.end_of_frame() == RtuFrame(5, bytes((0x41,)) + bytes(252))
    decoder.reset()
    decoder.feed(bytes(200))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(bytes(57))
    assert caught.value.kind == "oversize"
    assert decoder.buffered == MAX_RTU_FRAME  # never more than one frame is kept


@pytest.mark.parametrize("collected", ["", "01", "01 03", "01 83 02"])
def test_short_frame_on_silence(collected: str) -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 0001"))
    decoder.feed(h(collected))
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "short_frame"


def test_truncated_known_length_frame_fails_on_silence() -> None:
    decoder = RtuResponseDecoder(1, h("03 0000 000A"))
    assert decoder.feed(RESPONSE_000[:10]) is None
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "crc"


def test_a_crc_valid_three_byte_frame_is_short() -> None:
    # unit + CRC alone passes the CRC check but carries no function code.
    decoder = RtuResponseDecoder(1, h("41"))
    decoder.feed(append_crc(b"\x01"))
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "short_frame"


# ---- a response that answers another request of the same unit and function ------------


@pytest.mark.parametrize(
    ("request_pdu", "response"),
    [
        ("03 0000 000A", "03 02 1234"),  # byte count of a 1-register read
        ("04 0006 0002", "04 02 1122"),
        ("01 0013 0013", "01 01 05"),  # 19 coils need 3 bytes
        ("02 0000 0008", "02 02 FF 00"),  # 8 inputs need 1 byte
        ("17 0003 0006 000E 0003 06 00FF 00FF 00FF", "17 02 0001"),
        ("05 0012 FF00", "05 0013 FF00"),  # another coil
        ("05 0012 FF00", "05 0012 0000"),  # another value
        ("06 0007 1234", "06 0007 1235"),
        ("16 0004 00F2 0025", "16 0004 00F2 0026"),
        ("0F 0006 0009 02 11 01", "0F 0006 000A"),
        ("10 0002 0003 06 1122 3344 5566", "10 0003 0003"),
    ],
)
def test_decoder_rejects_a_response_to_another_request(request_pdu: str, response: str) -> None:
    decoder = RtuResponseDecoder(1, h(request_pdu))
    with pytest.raises(ResponseError) as caught:
        decoder.feed(encode_rtu(1, h(response)))
    assert caught.value.kind == "mismatch"


def test_a_damaged_answer_is_told_from_noise() -> None:
    request = h("03 0000 0002")
    answer = encode_rtu(1, h("03 04 0001 0002"))
    damaged = RtuResponseDecoder(1, request)
    with pytest.raises(ResponseError):
        damaged.feed(answer[:-1] + bytes((answer[-1] ^ 0xFF,)))
    assert damaged.looks_like_answer  # the answer itself, its CRC broken on the line
    noise = RtuResponseDecoder(1, request)
    with pytest.raises(ResponseError):
        noise.feed(h("02 03 02 0000 0000"))
    assert not noise.looks_like_answer  # another unit's address: noise before the answer


def test_a_write_file_record_answer_must_echo_the_request() -> None:
    request = h("15 0D 06 0004 0007 0003 06AF 04BE 100D")
    decoder = RtuResponseDecoder(1, request)
    other = h("15 0D 06 0004 0008 0003 06AF 04BE 100D")  # another record's late echo
    with pytest.raises(ResponseError) as caught:
        decoder.feed(encode_rtu(1, other))
    assert caught.value.kind == "mismatch"
    decoder.reset()
    assert decoder.feed(encode_rtu(1, request)) == RtuFrame(1, request)


# ---- noise in front of the answer (a transceiver turning around) ----------------------


ANSWER_REQUEST = h("03 0064 0002")
ANSWER = encode_rtu(1, h("03 04 0064 0065"))


@pytest.mark.parametrize("noise", ["FF", "00", "FE 00", "FF 00 55", "01 03 02", "01 83"])
@pytest.mark.parametrize("split", [False, True], ids=["one_read", "two_reads"])
def test_the_answer_right_behind_noise_is_found(noise: str, split: bool) -> None:
    """A byte or two from a transceiver turning around, or the start of an answer that
    broke off, runs straight into the answer: skipped as noise, the answer is taken."""
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    chunks = [h(noise), ANSWER] if split else [h(noise) + ANSWER]
    happened = decode_as_the_core_does(decoder, chunks)
    assert happened == ["noise", RtuFrame(1, h("03 04 0064 0065"))]


def test_the_answer_behind_noise_may_come_in_single_bytes() -> None:
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    chunks = [h("FF")] + [bytes((byte,)) for byte in ANSWER]
    happened = decode_as_the_core_does(decoder, chunks)
    assert happened == ["noise", RtuFrame(1, h("03 04 0064 0065"))]


def test_a_damaged_answer_with_the_answers_start_in_its_data_still_fails_at_once() -> None:
    """``01 03`` inside the data of a damaged answer is no answer: nothing whole and valid
    starts there, so the frame is the answer itself, damaged (retried at once)."""
    answer = encode_rtu(1, h("03 04 0103 0000"))
    damaged = answer[:-1] + bytes((answer[-1] ^ 0xFF,))
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    with pytest.raises(ResponseError) as caught:
        decoder.feed(damaged)
    assert caught.value.kind == "crc"
    assert decoder.looks_like_answer


def test_noise_that_contains_the_units_address_is_still_skipped() -> None:
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    happened = decode_as_the_core_does(decoder, [h("01 FF 01") + ANSWER])
    assert happened[-1] == RtuFrame(1, h("03 04 0064 0065"))
    assert set(happened[:-1]) == {"noise"}


@pytest.mark.parametrize("burst", ["FF 00 55", "00", "FE FF"])
def test_a_burst_shorter_than_any_answer_ended_by_silence_is_noise(burst: str) -> None:
    """Not the start of the answer (another first byte) and too short to be any answer:
    noise, so the wait for the answer goes on (no retry that would collide with it)."""
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    decoder.feed(h(burst))
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "noise"


def test_a_whole_answer_behind_noise_of_unknown_length_is_taken_without_the_silence() -> None:
    """Noise whose length cannot be told would collect until silence; the whole answer
    behind it is found as soon as it is in."""
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    with pytest.raises(ResponseError) as caught:
        decoder.feed(h("FF 00 55") + ANSWER)  # function 0: a length nobody can tell
    assert caught.value.kind == "noise"
    assert decoder.leftover == ANSWER


def test_on_silence_the_start_of_the_answer_behind_noise_is_followed() -> None:
    """A USB adapter may hand over the answer's first bytes, then the rest after a pause."""
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    assert decoder.feed(h("FF 00 55") + ANSWER[:2]) is None
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "noise"
    assert decoder.leftover == ANSWER[:2]


def test_noise_is_searched_only_near_the_frames_start() -> None:
    """Past ``MAX_NOISE`` bytes the frame in front is not noise from a turnaround: the
    answer behind it is not looked for (what it is stays a garbled frame)."""
    near = RtuResponseDecoder(1, ANSWER_REQUEST)
    with pytest.raises(ResponseError) as caught:
        near.feed(bytes(MAX_NOISE) + ANSWER)
    assert caught.value.kind == "noise"
    far = RtuResponseDecoder(1, ANSWER_REQUEST)
    assert far.feed(bytes(MAX_NOISE + 1) + ANSWER) is None  # function 0: silence ends it
    with pytest.raises(ResponseError) as caught:
        far.end_of_frame()
    assert caught.value.kind == "crc"


def test_a_late_answer_behind_noise_is_still_told_from_the_answer() -> None:
    """What the noise hid must pass every check: a late answer to a shorter read is
    skipped as a mismatch, never taken."""
    decoder = RtuResponseDecoder(1, ANSWER_REQUEST)
    late = encode_rtu(1, h("03 02 0001"))
    happened = decode_as_the_core_does(decoder, [h("FF") + late + ANSWER])
    assert happened == ["noise", "mismatch", RtuFrame(1, h("03 04 0064 0065"))]
