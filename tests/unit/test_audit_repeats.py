"""Repeated refusals and denials counted per source and interval, with literal times."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.audit_record import AuditOutcome, Pending, Record, refused_record
from gateway.core.audit_repeats import KINDS_PER_SOURCE, Occurrence, Repeats

T0 = 1_800_000_000.0


def denial(source: str, port: int, unit: int, pdu: bytes, now: float) -> tuple[Occurrence, Record]:
    peer = f"{source}:{port}"
    pending = Pending(now, "ro", peer, None, unit, pdu, None, None)
    kind = (("listener", "ro"), ("outcome", "denied"), ("reason", "read_only"), ("code", 1),
            ("unit", unit), ("function", pdu[0]))  # fmt: skip
    record = pending.record(AuditOutcome.DENIED, 1, "read_only")
    return Occurrence(source, "request", kind, (peer, pdu), now), record


def refusal(source: str, now: float) -> tuple[Occurrence, Record]:
    kind = (("listener", "fenced"), ("reason", "source_not_allowed"), ("at", "accept"))
    record = refused_record(now, "fenced", source, "source_not_allowed")
    return Occurrence(source, "connection_refused", kind, None, now), record


def given_back(record: Record) -> Callable[[], Record]:
    return lambda: record


def feed(repeats: Repeats, events: list[tuple[Occurrence, Record]]) -> list[Record]:
    written: list[Record] = []
    for occurrence, record in events:
        written += repeats.note(occurrence, given_back(record))
    return written + repeats.flush()


def test_a_flood_of_one_refusal_is_one_record_then_one_per_interval() -> None:
    events = [refusal("10.0.0.9", T0 + n / 1000) for n in range(2500)]  # 2.5 s, 1,000/s
    written = feed(Repeats(), events)
    # The first of each interval at once; the interval's other 999 in one record after it.
    assert [r.get("repeats") for r in written] == [None, 999, None, 999, None, 499]
    assert sum(r.get("repeats", 1) for r in written) == 2500  # nothing lost
    tally = written[1]
    assert tally["event"] == "connection_refused" and tally["source"] == "10.0.0.9"
    assert tally["first"] == "2027-01-15T08:00:00.001Z"
    assert tally["last"] == tally["time"] == "2027-01-15T08:00:00.999Z"
    assert (tally["reason"], tally["at"], tally["listener"]) == ("source_not_allowed", "accept",
                                                                "fenced")  # fmt: skip


def test_denials_keep_event_and_outcome_and_drop_only_what_differed() -> None:
    write = bytes.fromhex("06 0001 0005")
    same = [denial("10.0.0.9", 5000, 1, write, T0 + n / 100) for n in range(3)]
    other_ports = [denial("10.0.0.9", 5000 + n, 1, write, T0 + n / 100) for n in range(3)]
    kept, dropped = feed(Repeats(), same)[1], feed(Repeats(), other_ports)[1]
    assert (kept["event"], kept["outcome"], kept["repeats"]) == ("request", "denied", 2)
    assert kept["peer"] == "10.0.0.9:5000" and kept["values"] == [5]
    assert (dropped["event"], dropped["outcome"], dropped["repeats"]) == ("request", "denied", 2)
    assert "peer" not in dropped and "values" not in dropped and "addresses" not in dropped
    assert dropped["source"] == "10.0.0.9" and dropped["function"] == 6 and dropped["unit"] == 1


def test_many_kinds_from_one_source_stay_within_the_bound_and_sources_are_apart() -> None:
    events = []
    for n in range(3000):  # 1.5 s, every write function to 100 units
        function = (5, 6, 15, 16)[n % 4]
        pdu = bytes((function, 0, 1, 0, 1, 2, 0, 1)) if function in (15, 16) else bytes(
            (function, 0, 1, 0, 0))  # fmt: skip
        events.append(denial("10.0.0.9", 5000, 1 + n % 100, pdu, T0 + n / 2000))
    events += [refusal("10.0.0.8", T0 + 0.5)] * 3
    written = feed(Repeats(), events)
    by_source = Counter(r.get("source") or r["peer"].rsplit(":", 1)[0] for r in written)
    assert by_source["10.0.0.8"] == 2  # another source's refusals: its own records
    mine = [r for r in written if str(r.get("source", r.get("peer"))).startswith("10.0.0.9")]
    assert sum(r.get("repeats", 1) for r in mine) == 3000
    assert len(mine) <= 2 * (2 * KINDS_PER_SOURCE + 2)  # two intervals
    overflow = [r for r in mine if "unit" not in r]
    assert overflow and all(r["event"] == "request" and r["outcome"] == "denied" for r in overflow)


@given(st.lists(st.tuples(st.sampled_from(["a", "b", "c"]), st.integers(0, 30),
                          st.integers(0, 4000)), max_size=300))  # fmt: skip
def test_repeats_add_up_to_the_events_and_each_interval_is_bounded_per_source(
    events: list[tuple[str, int, int]],
) -> None:
    repeats = Repeats()
    written: list[tuple[float, Record]] = []
    for source, unit, millis in sorted(events, key=lambda e: e[2]):
        now = T0 + millis / 1000
        occurrence, record = denial(source, 1, unit, bytes((6, 0, 1, 0, 0)), now)
        written += [(now, r) for r in repeats.note(occurrence, given_back(record))]
    written += [(T0 + 10, r) for r in repeats.flush()]
    for source in "abc":
        mine = [(at, r) for at, r in written if r.get("source", r.get("peer", "")[:1]) == source]
        assert sum(r.get("repeats", 1) for _, r in mine) == sum(e[0] == source for e in events)
        per_second = Counter(int(at - T0) for at, _ in mine if at < T0 + 10)
        assert all(count <= 50 for count in per_second.values())
