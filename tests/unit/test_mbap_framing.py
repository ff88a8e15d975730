"""MBAP as a line's framing (``kind = "tcp"``): the gateway's own transaction ids downstream.

The decoder takes only the answer with the transaction id on the wire; the line core,
driven with literal times, skips a stale answer and takes the right one after it.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.config import LineConfig
from gateway.core.errors import ResponseError
from gateway.core.framing import LineKind, framing_for, mbap_framing
from gateway.core.line import LineCore, LineRequest
from gateway.core.mbap import MbapResponseDecoder, TransactionIds, encode_mbap
from gateway.core.outcome import LineEvent, Outcome
from gateway.core.rtu import RtuFrame

READ = struct.pack(">BHH", 3, 0x6B, 3)
ANSWER = bytes.fromhex("0306022B00000064")


def test_each_request_gets_the_next_transaction_id_and_wraps() -> None:
    ids = TransactionIds(0xFFFE)
    assert ids.encode(17, READ) == bytes.fromhex("FFFF 0000 0006 11 03006B0003")
    assert ids.encode(17, READ)[:2] == b"\x00\x00"
    assert ids.encode(17, READ)[:2] == b"\x00\x01"


def test_framing_for_tcp_is_new_for_each_line() -> None:
    first, second = framing_for("tcp"), framing_for("tcp")
    assert first.kind is LineKind.TCP and first is not second
    assert first.encode(1, READ)[:2] == second.encode(1, READ)[:2] == b"\x00\x01"


def test_only_the_answer_with_the_transaction_id_on_the_wire_is_taken() -> None:
    decoder = MbapResponseDecoder(7, READ)
    stale = encode_mbap(6, 17, ANSWER)
    with pytest.raises(ResponseError) as caught:
        decoder.feed(stale + encode_mbap(7, 17, ANSWER)[:3])
    assert caught.value.kind == "unexpected_tid"
    leftover = decoder.leftover
    decoder.reset()
    assert decoder.feed(leftover) is None
    assert decoder.feed(encode_mbap(7, 17, ANSWER)[3:]) == RtuFrame(17, ANSWER)


@pytest.mark.parametrize(
    ("adu", "kind"),
    [
        (bytes.fromhex("0007 0001 0006 11 0306022B0000"), "bad_header"),  # protocol id 1
        (bytes.fromhex("0007 0000 0100 11"), "bad_header"),  # length 256
        (encode_mbap(7, 17, bytes.fromhex("0402022B")), "unexpected_function"),
        (encode_mbap(7, 17, bytes.fromhex("0302022B")), "mismatch"),  # 1 register, 3 asked
    ],
)
def test_frames_that_are_not_the_answer(adu: bytes, kind: str) -> None:
    with pytest.raises(ResponseError) as caught:
        MbapResponseDecoder(7, READ).feed(adu)
    assert caught.value.kind == kind


def test_an_exception_answer_and_any_unit_id() -> None:
    assert MbapResponseDecoder(7, READ).feed(encode_mbap(7, 255, b"\x83\x02")) == RtuFrame(
        255, b"\x83\x02"
    )


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 0xFFFF),
    st.integers(0, 255),
    st.integers(1, 125).flatmap(lambda n: st.binary(min_size=2 * n, max_size=2 * n)),
    st.lists(st.integers(0, 270), max_size=8),
)
def test_round_trip_under_any_chunking(tid: int, unit: int, data: bytes, cuts: list[int]) -> None:
    request = struct.pack(">BHH", 3, 0, len(data) // 2)
    answer = bytes((3, len(data))) + data
    adu = encode_mbap(tid, unit, answer)
    points = sorted({cut % (len(adu) + 1) for cut in cuts})
    chunks = [adu[a:b] for a, b in zip([0, *points], [*points, len(adu)], strict=True)]
    decoder = MbapResponseDecoder(tid, request)
    frames = [frame for chunk in chunks if chunk and (frame := decoder.feed(chunk))]
    assert frames == [RtuFrame(unit, answer)]
    assert decoder.buffered <= 260


def test_the_core_skips_a_stale_answer_and_takes_its_own() -> None:
    config = LineConfig(name="t", device="tcp", baudrate=115200, timeout=0.5, retries=1)
    core = LineCore(config, -1.0, framing=mbap_framing())
    core.port_opened(-1.0)
    answers: list[tuple[bytes, str]] = []
    core.submit(LineRequest(17, READ, "m", lambda pdu, outcome: answers.append((pdu, outcome))), 0)
    assert [t.frame for t in core.transmits] == [encode_mbap(1, 17, READ)]
    core.handle_timer(core.get_timer() or 0.0)  # no answer: the retry goes as transaction 2
    assert [t.frame[:2] for t in core.transmits] == [b"\x00\x01", b"\x00\x02"]
    core.receive(encode_mbap(1, 17, ANSWER) + encode_mbap(2, 17, ANSWER), 0.9)
    for delivery in core.deliveries:
        delivery.request.reply(delivery.pdu, delivery.outcome)
    assert answers == [(ANSWER, Outcome.OK)]
    assert [n.detail for n in core.notes if n.event is LineEvent.DISCARDED] == ["unexpected_tid"]


@pytest.mark.parametrize("kind", ["tcp", "tls"])
def test_a_modbus_tcp_slave_gets_the_next_request_at_once(kind: str) -> None:
    """No serial wire behind the socket: a request takes no transmission time to hold back."""
    config = LineConfig(name="t", device="plc:502", kind=kind, timeout=0.5)  # 9600 baud
    core = LineCore(config, -1.0, framing=framing_for(kind))
    core.port_opened(-1.0)
    for master in ("a", "b"):
        core.submit(LineRequest(17, READ, master, lambda pdu, outcome: None), 0.0)
    assert [t.frame for t in core.transmits] == [encode_mbap(1, 17, READ)]
    core.transmits.clear()
    core.receive(encode_mbap(1, 17, ANSWER), 0.0002)
    assert [t.frame for t in core.transmits] == [encode_mbap(2, 17, READ)]  # at 0.2 ms
    assert core.get_timer() == pytest.approx(0.0002 + 0.5)  # the second one's timeout only
