"""The forwarder's decisions (``core.forwarding``), with literal times: transaction ids,
deadlines and answer matching on one client connection, and the masters' turns on a link."""

from __future__ import annotations

import struct

from gateway.core.forwarding import Answered, Flights, Late, Rounds, Stray
from gateway.core.mbap import MbapDecoder, MbapFrame, TransactionIds

READ_1 = struct.pack(">BHH", 3, 100, 1)
READ_2 = struct.pack(">BHH", 3, 100, 2)
WRITE = struct.pack(">BHH", 6, 7, 0x1234)


def answer_to(pdu: bytes, values: list[int]) -> bytes:
    return bytes((pdu[0], 2 * len(values))) + b"".join(v.to_bytes(2, "big") for v in values)


def decoded(adu: bytes) -> MbapFrame:
    decoder = MbapDecoder()
    decoder.feed(adu)
    frame = decoder.next_frame()
    assert frame is not None
    return frame


def test_each_request_has_its_own_id_and_only_its_answer_reaches_it() -> None:
    flights: Flights[str] = Flights()
    one = decoded(flights.send("one", 1, READ_1, 10.0))
    two = decoded(flights.send("two", 1, READ_2, 10.0))
    assert one.transaction_id != two.transaction_id
    assert (one.unit_id, one.pdu) == (1, READ_1)
    # Answers in any order, each to the request its id names.
    tid_two = two.transaction_id
    assert flights.match(MbapFrame(tid_two, 1, answer_to(READ_2, [5, 6]))) == Answered(
        "two", answer_to(READ_2, [5, 6])
    )
    assert len(flights) == 1
    # Its id, but not its answer (two registers for a read of one): out of step.
    wrong = flights.match(MbapFrame(one.transaction_id, 1, answer_to(READ_1, [1, 2])))
    assert isinstance(wrong, Stray) and "transaction id" in wrong.why
    assert isinstance(
        flights.match(MbapFrame(one.transaction_id, 2, answer_to(READ_1, [1]))), Stray
    )
    assert isinstance(flights.match(MbapFrame(999, 1, answer_to(READ_1, [1]))), Stray)
    # An exception from the server answers its request too.
    assert flights.match(MbapFrame(one.transaction_id, 1, bytes((0x83, 0x0B)))) == Answered(
        "one", bytes((0x83, 0x0B))
    )
    assert len(flights) == 0


def test_a_request_past_its_deadline_is_given_up_and_its_id_stays_reserved() -> None:
    flights: Flights[str] = Flights(ids=TransactionIds(start=0))
    first = decoded(flights.send("slow", 1, WRITE, 2.0)).transaction_id
    decoded(flights.send("later", 1, READ_1, 3.5))
    assert flights.get_timer() == 2.0
    assert flights.expire(1.999) == []
    assert flights.expire(2.0) == ["slow"]
    assert flights.get_timer() == 3.5
    # Its late answer is recognised (and counted as awaited), once.
    assert flights.match(MbapFrame(first, 1, WRITE)) == Late(expected=True)
    assert isinstance(flights.match(MbapFrame(first, 1, WRITE)), Stray)


def test_a_reserved_id_is_never_handed_out_and_the_oldest_reservation_goes_first() -> None:
    flights: Flights[int] = Flights(lost_kept=2, ids=TransactionIds(start=0xFFFF))
    # Ids 0, 1, 2 given up in turn: only the newest two stay reserved.
    for n in range(3):
        tid = decoded(flights.send(n, 1, READ_1, 1.0)).transaction_id
        assert tid == n
        assert flights.give_up(tid, expected=False) == n
    assert list(flights.reserved) == [1, 2]
    # The sequence wraps to 1 and 2 only after 65,536 others; forced there, they are skipped.
    flights.ids.current = 0
    assert decoded(flights.send(9, 1, READ_1, 1.0)).transaction_id == 3
    assert flights.match(MbapFrame(2, 1, answer_to(READ_1, [0]))) == Late(expected=False)


def test_taking_all_forgets_the_reservations_of_a_closed_connection() -> None:
    flights: Flights[str] = Flights()
    flights.send("a", 1, READ_1, 1.0)
    flights.expire(1.0)
    flights.send("b", 1, READ_1, 5.0)
    assert flights.take_all() == ["b"]
    assert not flights.outstanding and not flights.reserved
    assert flights.get_timer() == float("inf")


def test_the_masters_of_a_link_take_turns_and_keep_their_order() -> None:
    rounds: Rounds[str] = Rounds(bound=3)
    for n in range(3):
        assert rounds.add("busy", f"busy{n}", 10.0)
    assert not rounds.add("busy", "busy3", 10.0)  # its bound: waiting and outstanding
    assert rounds.add("quiet", "quiet0", 10.0)
    taken = [rounds.next() for _ in range(4)]
    assert [t[1] for t in taken if t is not None] == ["busy0", "quiet0", "busy1", "busy2"]
    assert rounds.next() is None and not rounds
    assert rounds.held("busy") == 3 and not rounds.add("busy", "busy3", 10.0)
    rounds.done("busy")
    assert rounds.held("busy") == 2 and rounds.add("busy", "busy3", 10.0)


def test_waiting_requests_expire_and_a_master_that_leaves_takes_its_own() -> None:
    rounds: Rounds[str] = Rounds(bound=8)
    rounds.add("a", "a0", 1.0)
    rounds.add("a", "a1", 2.0)
    rounds.add("b", "b0", 1.5)
    assert rounds.get_timer() == 1.0
    assert rounds.expire(1.5) == ["a0", "b0"]
    assert rounds.get_timer() == 2.0
    rounds.add("b", "b1", 3.0)
    assert rounds.leave("a") == ["a1"]
    assert list(rounds) == ["b"]
    assert rounds.take_all() == ["b1"] and not rounds
