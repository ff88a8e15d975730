"""Modbus ASCII: byte-exact frames with LRC, the decoder's checks, and the line core on ASCII.

The core is driven with literal times, as in ``test_line_core``.
"""

from __future__ import annotations

import struct
import tomllib

import pytest

from gateway.config import ConfigError, GatewayConfig, LineConfig, build_config
from gateway.core.ascii import AsciiResponseDecoder, decode_ascii, encode_ascii, lrc
from gateway.core.errors import ResponseError
from gateway.core.framing import ASCII, RTU, framing_for
from gateway.core.line import LineCore, LineRequest
from gateway.core.outcome import LineEvent, Outcome
from gateway.core.rtu import RtuFrame, encode_rtu
from gateway.core.timing import character_time


def load_config_text(text: str) -> GatewayConfig:
    return build_config(tomllib.loads(text), "gateway.toml")


READ_COILS = bytes.fromhex("0100020010")  # unit 1 in the vectors: FC 1, start 2, quantity 16


# --------------------------------------------------------------------------- the frame


def test_read_coils_vector() -> None:
    assert encode_ascii(1, READ_COILS) == b":010100020010EC\r\n"
    assert lrc(bytes.fromhex("010100020010")) == 0xEC


def test_specification_example_read_holding_registers() -> None:
    # Modbus over Serial Line v1.02, 6.2.2: unit 0x11 reads 3 registers at 0x006B.
    assert encode_ascii(0x11, bytes.fromhex("03006B0003")) == b":1103006B00037E\r\n"
    assert decode_ascii(b":1103006B00037E\r\n") == RtuFrame(0x11, bytes.fromhex("03006B0003"))


def test_lower_case_hex_is_accepted_and_upper_case_sent() -> None:
    decoder = AsciiResponseDecoder(0x11, bytes.fromhex("03006B0003"))
    answer = bytes.fromhex("0306022B00000064")
    wire = encode_ascii(0x11, answer)
    assert wire == wire.upper()
    assert decoder.feed(wire.lower().replace(b"\r\n", b"\r\n")) == RtuFrame(0x11, answer)


def decode_one(wire: bytes, unit: int = 1, request: bytes = READ_COILS) -> RtuFrame | None:
    return AsciiResponseDecoder(unit, request).feed(wire)


COILS_ANSWER = bytes.fromhex("0102CD6B")  # FC 1, 2 bytes of coils


def test_the_answer_decodes_in_any_pieces_and_keeps_what_follows() -> None:
    wire = encode_ascii(1, COILS_ANSWER)
    decoder = AsciiResponseDecoder(1, READ_COILS)
    assert decoder.feed(b"\x00\xff junk") is None  # outside a frame: ignored
    assert not decoder.waits_for_silence
    for index in range(len(wire) - 1):
        assert decoder.feed(wire[index : index + 1]) is None
    assert decoder.waits_for_silence  # inside a frame: the inter-character timeout runs
    assert decoder.buffered == len(wire) - 1
    assert decoder.feed(wire[-1:] + b":01") == RtuFrame(1, COILS_ANSWER)
    assert decoder.leftover == b":01"


@pytest.mark.parametrize(
    ("wire", "kind"),
    [
        (b":010102CD6B00\r\n", "crc"),  # wrong LRC
        (b":010102CD6BG4\r\n", "bad_char"),
        (b":010102CD6BC4\n", "bad_char"),  # LF without CR
        (b":0101\r\n", "short_frame"),
        (b":020102CD6B" + b"%02X\r\n" % lrc(bytes.fromhex("020102CD6B")), "unexpected_unit"),
        (encode_ascii(1, bytes.fromhex("0302CD6B")), "unexpected_function"),
        (encode_ascii(1, bytes.fromhex("0101CD")), "mismatch"),  # 1 byte, 2 asked for
    ],
)
def test_frames_that_are_not_the_answer_are_refused(wire: bytes, kind: str) -> None:
    with pytest.raises(ResponseError) as caught:
        decode_one(wire)
    assert caught.value.kind == kind


def test_a_bad_lrc_on_the_awaited_answer_looks_like_the_answer() -> None:
    decoder = AsciiResponseDecoder(1, READ_COILS)
    with pytest.raises(ResponseError):
        decoder.feed(b":010102CD6B00\r\n")
    assert decoder.looks_like_answer
    other = AsciiResponseDecoder(1, READ_COILS)
    with pytest.raises(ResponseError):
        other.feed(b":010103CD6B00\r\n")  # a byte count of 3 with 2 bytes
    assert not other.looks_like_answer


def test_a_colon_inside_a_frame_restarts_it() -> None:
    wire = encode_ascii(1, COILS_ANSWER)
    decoder = AsciiResponseDecoder(1, READ_COILS)
    with pytest.raises(ResponseError) as caught:
        decoder.feed(b":0101" + wire)
    assert caught.value.kind == "restarted"
    assert decoder.leftover == wire
    decoder.reset()
    assert decoder.feed(decoder.leftover or wire) == RtuFrame(1, COILS_ANSWER)


def test_more_than_513_characters_is_oversize_and_the_next_frame_is_found() -> None:
    wire = encode_ascii(1, COILS_ANSWER)
    decoder = AsciiResponseDecoder(1, READ_COILS)
    assert decoder.feed(b":" + b"0" * 511) is None  # 512 characters: still a frame
    with pytest.raises(ResponseError) as caught:
        decoder.feed(b"00\r\n" + wire)
    assert caught.value.kind == "oversize"
    leftover = decoder.leftover
    decoder.reset()
    assert decoder.feed(leftover) == RtuFrame(1, COILS_ANSWER)


def test_the_inter_character_timeout_abandons_a_frame() -> None:
    decoder = AsciiResponseDecoder(1, READ_COILS)
    decoder.feed(b":0101")
    with pytest.raises(ResponseError) as caught:
        decoder.end_of_frame()
    assert caught.value.kind == "incomplete"


# --------------------------------------------------------------------------- configuration


def test_kind_ascii_defaults_to_7e1_and_a_longer_auto_timeout() -> None:
    config = load_config_text('[lines.a]\ndevice = "/dev/null"\nkind = "ascii"\n')
    line = config.lines[0]
    assert (line.kind, line.data_bits, line.parity, line.stop_bits) == ("ascii", 7, "E", 1)
    assert line.timeout == pytest.approx(0.634)  # 513 characters at 9600 7E1 + 0.1 s
    assert line.silence == 1.0  # the inter-character timeout
    assert line.gap == pytest.approx(character_time(9600, 7, "E", 1))
    rtu = load_config_text('[lines.a]\ndevice = "/dev/null"\n').lines[0]
    assert (rtu.kind, rtu.data_bits, rtu.parity, rtu.timeout) == ("rtu", 8, "N", 0.367)


def test_inter_char_timeout_is_configurable() -> None:
    text = '[lines.a]\ndevice = "/dev/null"\nkind = "ascii"\ninter_char_timeout = 0.25\n'
    assert load_config_text(text).lines[0].silence == 0.25


def test_an_unknown_kind_names_the_key_and_the_choices() -> None:
    with pytest.raises(ConfigError, match=r"lines\.a\.kind.*'rtu-ish'.*rtu, ascii"):
        load_config_text('[lines.a]\ndevice = "/dev/null"\nkind = "rtu-ish"\n')


def test_framing_for_each_kind() -> None:
    assert framing_for("rtu") is RTU
    assert framing_for("ascii") is ASCII
    assert RTU.encode is encode_rtu  # the RTU path has no indirection


# --------------------------------------------------------------------------- the core


def ascii_line() -> tuple[LineCore, list[tuple[bytes, str]]]:
    config = LineConfig(
        name="a", device="/dev/null", baudrate=9600, data_bits=7, parity="E", kind="ascii",
        timeout=0.5, retries=1,
    )  # fmt: skip
    core = LineCore(config, -1.0, framing=ASCII)
    core.port_opened(-1.0)
    return core, []


def submit(core: LineCore, answers: list[tuple[bytes, str]], pdu: bytes, now: float) -> None:
    def reply(answer: bytes, outcome: str) -> None:
        answers.append((answer, outcome))

    core.submit(LineRequest(1, pdu, "m", reply), now)


def flush(core: LineCore) -> None:
    for delivery in core.deliveries:
        delivery.request.reply(delivery.pdu, delivery.outcome)
    core.deliveries.clear()


def test_the_core_sends_ascii_and_takes_the_answer_in_pieces() -> None:
    core, answers = ascii_line()
    submit(core, answers, READ_COILS, 0.0)
    assert [t.frame for t in core.transmits] == [b":010100020010EC\r\n"]
    char = character_time(9600, 7, "E", 1)
    assert core.get_timer() == pytest.approx(17 * char + 0.5)  # timed in characters
    wire = encode_ascii(1, COILS_ANSWER)
    core.receive(b"\xff" + wire[:5], 0.05)  # noise before ':' is ignored
    assert core.get_timer() == pytest.approx(17 * char + 0.5)  # the deadline comes first
    core.receive(wire[5:], 0.06)
    flush(core)
    assert answers == [(COILS_ANSWER, Outcome.OK)]


def test_a_frame_whose_characters_stop_is_dropped_after_the_inter_character_timeout() -> None:
    config = LineConfig(
        name="a", device="/dev/null", baudrate=9600, kind="ascii", timeout=5.0, retries=0,
        inter_char_timeout=0.2,
    )  # fmt: skip
    core = LineCore(config, -1.0, framing=ASCII)
    core.port_opened(-1.0)
    answers: list[tuple[bytes, str]] = []
    submit(core, answers, READ_COILS, 0.0)
    core.receive(b":0101", 0.1)
    timer = core.get_timer()
    assert timer is not None
    assert timer == pytest.approx(0.3)
    core.handle_timer(timer)
    assert [n.detail for n in core.notes if n.event is LineEvent.DISCARDED] == ["incomplete"]
    # The real answer may still follow the broken frame: it is taken.
    core.receive(encode_ascii(1, COILS_ANSWER), 0.31)
    flush(core)
    assert answers == [(COILS_ANSWER, Outcome.OK)]


def test_a_restarted_frame_is_counted_and_the_answer_after_it_taken() -> None:
    core, answers = ascii_line()
    submit(core, answers, struct.pack(">BHH", 1, 2, 16), 0.0)
    core.receive(b":01" + encode_ascii(1, COILS_ANSWER), 0.05)
    flush(core)
    assert answers == [(COILS_ANSWER, Outcome.OK)]
    assert [n.detail for n in core.notes if n.event is LineEvent.DISCARDED] == ["restarted"]
