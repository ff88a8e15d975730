"""Fair share at the connection limit: literal snapshots, then invariants with hypothesis."""

from __future__ import annotations

from dataclasses import replace

from hypothesis import given
from hypothesis import strategies as st

from gateway.config import build_config, config_warnings
from gateway.core.connection_share import (
    ADMIT,
    Evict,
    OpenConnection,
    Refusal,
    Refuse,
    ShareLimits,
    Verdict,
    admit_connection,
    has_free_slot,
)

A, B, C = "10.0.0.1", "10.0.0.2", "10.0.0.3"
FULL_4 = ShareLimits(max_connections=4, evict_min_idle=10.0)


def idle(source: str, seconds: float) -> OpenConnection:
    return OpenConnection(source, seconds, 0)


def busy(source: str) -> OpenConnection:
    return OpenConnection(source, 0.0, 1)


def silent(source: str, opened: float) -> OpenConnection:
    """A connection open ``opened`` seconds that has never sent a request."""
    return OpenConnection(source, opened, 0, used=False)


# --------------------------------------------------------------------------- free slots


def test_while_slots_are_free_every_newcomer_is_admitted_whatever_its_source_holds() -> None:
    limits = ShareLimits(max_connections=100)
    snapshot = [busy(A)] * 99
    assert admit_connection(A, limits, snapshot) == ADMIT
    assert has_free_slot(limits, total=99, held=99)
    assert not has_free_slot(limits, total=100, held=0)


def test_an_explicit_cap_still_refuses_its_source_beyond_it() -> None:
    limits = ShareLimits(max_connections=100, max_per_source=16)
    snapshot = [idle(A, 60.0)] * 16
    assert admit_connection(A, limits, snapshot) == Refuse(Refusal.MAX_PER_SOURCE)
    assert admit_connection(B, limits, snapshot) == ADMIT
    assert not has_free_slot(limits, total=16, held=16)
    assert has_free_slot(limits, total=16, held=15)


# --------------------------------------------------------------------------- at the limit


def test_a_single_source_evicts_its_own_longest_idle_connection_as_before() -> None:
    snapshot = [idle(A, 11.0), idle(A, 30.0), idle(A, 12.0), busy(A)]
    assert admit_connection(A, FULL_4, snapshot) == Evict(1)


def test_a_newcomer_from_the_heaviest_source_is_refused_when_none_of_its_own_may_go() -> None:
    # B's connection idle for an hour is not the heaviest's to take.
    snapshot = [idle(A, 1.0), idle(A, 2.0), busy(A), idle(B, 3600.0)]
    assert admit_connection(A, FULL_4, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_a_newcomer_from_a_lighter_source_displaces_the_heaviest_even_young() -> None:
    snapshot = [idle(A, 1.0), idle(A, 2.0), idle(A, 0.5), idle(B, 3600.0)]
    # C holds none, A holds three (>= 0 + 2): A's longest-idle goes, however young.
    assert admit_connection(C, FULL_4, snapshot) == Evict(1, over_share=True)
    # B holds one, A three (>= 1 + 2): the same.
    assert admit_connection(B, FULL_4, snapshot) == Evict(1, over_share=True)


def test_the_heaviest_source_yields_its_old_idle_connection_before_anyone_else() -> None:
    snapshot = [idle(A, 20.0), idle(A, 15.0), idle(B, 3600.0), idle(C, 3600.0)]
    assert admit_connection(C, FULL_4, snapshot) == Evict(0)


def test_when_the_heaviest_has_everything_in_flight_the_next_heaviest_yields() -> None:
    limits = ShareLimits(max_connections=6, evict_min_idle=10.0)
    snapshot = [busy(A), busy(A), busy(A), idle(B, 1.0), idle(B, 2.0), idle(C, 0.1)]
    # D holds none: A cannot give anything, B holds two (>= 0 + 2): its longest-idle goes.
    assert admit_connection("10.0.0.4", limits, snapshot) == Evict(4, over_share=True)
    # C holds one: B holds only one more, so only a connection idle for 10 s would do.
    assert admit_connection(C, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_a_source_one_heavier_yields_only_what_is_idle_for_evict_min_idle() -> None:
    snapshot = [idle(A, 9.0), idle(A, 2.0), idle(B, 1.0)]
    limits = ShareLimits(max_connections=3, evict_min_idle=10.0)
    assert admit_connection(B, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)
    later = [idle(A, 10.0), idle(A, 3.0), idle(B, 2.0)]
    assert admit_connection(B, limits, later) == Evict(0)


def test_a_source_no_heavier_than_the_newcomers_is_never_touched() -> None:
    snapshot = [busy(A), busy(A), idle(B, 3600.0), idle(B, 3600.0)]
    assert admit_connection(A, FULL_4, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_a_newcomer_may_make_room_among_its_own_after_the_heavier_sources() -> None:
    snapshot = [busy(A), busy(A), busy(A), idle(B, 11.0)]
    assert admit_connection(B, FULL_4, snapshot) == Evict(3)


def test_connections_with_requests_in_flight_are_never_closed() -> None:
    snapshot = [busy(A), busy(A), busy(A), busy(B)]
    assert admit_connection(C, FULL_4, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_when_full_refuse_never_evicts() -> None:
    limits = ShareLimits(max_connections=4, evict=False)
    snapshot = [idle(A, 3600.0)] * 4
    assert admit_connection(B, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_equal_heavy_sources_yield_the_one_idle_longest_first() -> None:
    snapshot = [idle(A, 1.0), idle(A, 2.0), idle(B, 5.0), idle(B, 4.0)]
    assert admit_connection(C, FULL_4, snapshot) == Evict(2, over_share=True)


def test_the_explicit_cap_is_checked_before_the_share() -> None:
    limits = ShareLimits(max_connections=4, max_per_source=1)
    snapshot = [idle(A, 1.0), idle(A, 2.0), idle(A, 3.0), idle(B, 3600.0)]
    assert admit_connection(B, limits, snapshot) == Refuse(Refusal.MAX_PER_SOURCE)


# --------------------------------------------------------------------------- never used


def test_silent_connections_from_many_sources_never_displace_a_busy_host() -> None:
    # A SCADA host's three masters poll (idle a moment between polls); 17 sources hold
    # one silent connection each. The share rule alone would take the SCADA host's.
    limits = ShareLimits(max_connections=20, evict_min_idle=10.0)
    scada = [idle("10.0.0.1", 0.2)] * 3
    snapshot = scada + [silent(f"10.0.1.{n}", 5.0 + n) for n in range(17)]
    for policy in (True, False):
        verdict = admit_connection("10.0.2.1", replace(limits, evict=policy), snapshot)
        # The newcomer holds none, under 20 / 19: the oldest silent one of a heavier source.
        assert verdict == Evict(19, never_used=True)
    # The SCADA host reconnecting is over its share (3 of 20 / 18): refused, no one closed.
    assert admit_connection("10.0.0.1", limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_under_refuse_a_lighter_newcomer_takes_the_heaviest_sources_oldest_silent_one() -> None:
    limits = ShareLimits(max_connections=6, evict=False)
    snapshot = [silent(A, 1.0), silent(A, 3.0), silent(A, 2.0), idle(A, 60.0), idle(B, 9.0),
                silent(B, 50.0)]  # fmt: skip
    assert admit_connection(C, limits, snapshot) == Evict(1, never_used=True)
    # B holds two: under 6 / 2, and A holds more: A's oldest silent one, not B's own.
    assert admit_connection(B, limits, snapshot) == Evict(1, never_used=True)
    # A is the heaviest (4 of 6 / 2): refused, as "refuse" says.
    assert admit_connection(A, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)


def test_the_heaviest_source_with_a_silent_connection_yields_it_before_anyone_else() -> None:
    limits = ShareLimits(max_connections=6)
    snapshot = [busy(A), idle(A, 60.0), idle(A, 60.0), silent(B, 1.0), silent(B, 0.5),
                silent(C, 30.0)]  # fmt: skip
    # A is heaviest but has no silent connection; B holds two: its oldest silent one.
    assert admit_connection("10.0.0.4", limits, snapshot) == Evict(3, never_used=True)


def test_while_a_silent_connection_is_open_no_used_one_is_closed_for_the_share() -> None:
    # A newcomer at its share: the share rule runs, over the silent connections only.
    limits = ShareLimits(max_connections=4, evict_min_idle=10.0)
    snapshot = [idle(A, 3600.0), idle(A, 3600.0), silent(B, 1.0), idle(B, 3600.0)]
    assert admit_connection(B, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)
    old = [idle(A, 3600.0), idle(A, 3600.0), silent(B, 11.0), idle(B, 3600.0)]
    assert admit_connection(B, limits, old) == Evict(2)
    # Once no silent connection is open, the share rule applies to used ones as before.
    used = [idle(A, 3600.0), idle(A, 3600.0), idle(B, 1.0), idle(B, 3600.0)]
    assert admit_connection(B, limits, used) == Evict(3)


def test_a_source_no_heavier_than_the_newcomers_keeps_its_silent_connections() -> None:
    limits = ShareLimits(max_connections=4, evict=False)
    snapshot = [silent(A, 9.0), idle(B, 1.0), idle(C, 1.0), idle("10.0.0.4", 1.0)]
    assert admit_connection(B, limits, snapshot) == Refuse(Refusal.MAX_CONNECTIONS)
    assert admit_connection("10.0.0.5", limits, snapshot) == Evict(0, never_used=True)


# --------------------------------------------------------------------------- the pair's links

PEER = "10.0.0.9"  # the redundancy peer: its links carry the masters it admitted


def test_the_peers_links_have_a_budget_of_their_own() -> None:
    """The others hold every slot: a link of the peer still gets in, up to
    max_connections of its own, and the explicit cap per address does not apply to it."""
    limits = replace(FULL_4, max_per_source=1)
    others = [busy(A), busy(A), busy(B), busy(C)]
    assert admit_connection(PEER, limits, others, pair={PEER}) == ADMIT
    links = [busy(PEER)] * 3
    assert admit_connection(PEER, limits, others + links, pair={PEER}) == ADMIT
    assert admit_connection(PEER, limits, others + links + [busy(PEER)], pair={PEER}) == Refuse(
        Refusal.MAX_CONNECTIONS
    )
    # Without the pair named, the same link is one more connection of a source.
    assert admit_connection(PEER, limits, others, pair=()) == Refuse(Refusal.MAX_CONNECTIONS)


def test_the_others_decide_as_if_the_peers_links_were_not_there() -> None:
    links = [idle(PEER, 99.0), idle(PEER, 99.0), idle(PEER, 99.0)]
    # Three of the others' four slots used: a newcomer is admitted, the links not counted.
    assert admit_connection(C, FULL_4, [*links, busy(A), busy(A), busy(B)], pair={PEER}) == ADMIT
    # At the others' limit, the victim is one of theirs (its index in the whole snapshot),
    # never a link of the peer however idle and numerous.
    snapshot = [links[0], idle(A, 20.0), links[1], idle(A, 30.0), busy(B), busy(A), links[2]]
    assert admit_connection(C, FULL_4, snapshot, pair={PEER}) == Evict(3)
    everything_busy = [links[0], busy(A), busy(A), busy(B), busy(B), links[1]]
    assert admit_connection(C, FULL_4, everything_busy, pair={PEER}) == Refuse(
        Refusal.MAX_CONNECTIONS
    )


def test_refusal_reasons_are_the_metric_labels() -> None:
    assert {reason.value for reason in Refusal} == {"max_connections", "max_per_source"}


# --------------------------------------------------------------------------- invariants

SOURCES = st.sampled_from([A, B, C, "10.0.0.4"])
CONNECTION = st.builds(
    OpenConnection,
    SOURCES,
    st.sampled_from([0.0, 0.5, 5.0, 9.99, 10.0, 60.0]),
    st.sampled_from([0, 0, 1, 3]),
    st.just(True),
)
#: Connections of any kind: a never-used one has nothing in flight.
ANY_CONNECTION = st.one_of(
    CONNECTION,
    st.builds(silent, SOURCES, st.sampled_from([0.0, 0.5, 5.0, 9.99, 10.0, 60.0])),
)
LIMITS = st.builds(
    ShareLimits,
    st.integers(1, 12),
    st.sampled_from([0, 0, 1, 3, 16]),
    st.booleans(),
    st.sampled_from([0.0, 10.0]),
)


def _full(limits: ShareLimits, connections: list[OpenConnection]) -> list[OpenConnection]:
    return connections[: limits.max_connections]


def _after(verdict: Verdict, connections: list[OpenConnection]) -> int:
    """The number of connections once the verdict is carried out."""
    if isinstance(verdict, Evict):
        return len(connections)
    return len(connections) + (verdict == ADMIT)


@given(SOURCES, LIMITS, st.lists(CONNECTION, max_size=14))
def test_the_count_never_exceeds_max_connections(
    source: str, limits: ShareLimits, connections: list[OpenConnection]
) -> None:
    snapshot = _full(limits, connections)
    assert _after(admit_connection(source, limits, snapshot), snapshot) <= limits.max_connections


@given(SOURCES, LIMITS, st.lists(CONNECTION, max_size=14))
def test_a_victim_is_idle_and_its_source_no_lighter_than_the_newcomers(
    source: str, limits: ShareLimits, connections: list[OpenConnection]
) -> None:
    snapshot = _full(limits, connections)
    verdict = admit_connection(source, limits, snapshot)
    if not isinstance(verdict, Evict):
        return
    assert limits.evict and len(snapshot) == limits.max_connections
    victim = snapshot[verdict.index]
    counts = {s: sum(c.source == s for c in snapshot) for s in {c.source for c in snapshot}}
    held = counts.get(source, 0)
    assert victim.in_flight == 0
    if victim.source == source:
        assert victim.idle >= limits.evict_min_idle
    else:
        assert counts[victim.source] > held  # never from a source no heavier than its own
        if victim.idle < limits.evict_min_idle:
            assert counts[victim.source] >= held + 2 and verdict.over_share
    # The longest-idle of its source among those with nothing in flight.
    assert all(
        c.idle <= victim.idle for c in snapshot if c.source == victim.source and not c.in_flight
    )


@given(SOURCES, st.integers(1, 12), st.lists(CONNECTION, max_size=14))
def test_a_newcomer_is_never_refused_while_a_source_two_heavier_has_an_idle_connection(
    source: str, max_connections: int, connections: list[OpenConnection]
) -> None:
    limits = ShareLimits(max_connections, evict_min_idle=10.0)
    snapshot = _full(limits, connections)
    held = sum(c.source == source for c in snapshot)
    heavy = {
        c.source
        for c in snapshot
        if c.source != source
        and c.in_flight == 0
        and sum(o.source == c.source for o in snapshot) >= held + 2
    }
    if heavy:
        assert not isinstance(admit_connection(source, limits, snapshot), Refuse)


@given(SOURCES, st.integers(2, 12), st.lists(SOURCES, min_size=12, max_size=12))
def test_a_source_within_its_fair_share_gets_in_when_the_others_are_idle(
    source: str, max_connections: int, sources: list[str]
) -> None:
    snapshot = [idle(s, 1.0) for s in sources[:max_connections]]  # full, all young
    held = sum(s == source for s in sources[:max_connections])
    share = max_connections // len({*sources[:max_connections], source})
    verdict = admit_connection(source, ShareLimits(max_connections), snapshot)
    if held + 1 <= share:
        assert isinstance(verdict, Evict) and snapshot[verdict.index].source != source
    else:  # nothing old enough: a source at or over its share gets no one's slot
        counts = [sum(s == other for s in sources[:max_connections]) for other in sources]
        if max(counts) < held + 2:
            assert verdict == Refuse(Refusal.MAX_CONNECTIONS)


def _counts(snapshot: list[OpenConnection]) -> dict[str, int]:
    return {s: sum(c.source == s for c in snapshot) for s in {c.source for c in snapshot}}


def _under_share(source: str, limits: ShareLimits, snapshot: list[OpenConnection]) -> bool:
    counts = _counts(snapshot)
    sources = len(counts.keys() | {source})
    return counts.get(source, 0) * sources < limits.max_connections


@given(SOURCES, LIMITS, st.lists(ANY_CONNECTION, max_size=14))
def test_no_used_connection_is_closed_while_a_never_used_one_is_open(
    source: str, limits: ShareLimits, connections: list[OpenConnection]
) -> None:
    snapshot = _full(limits, connections)
    verdict = admit_connection(source, limits, snapshot)
    assert _after(verdict, snapshot) <= limits.max_connections
    if not isinstance(verdict, Evict):
        return
    victim = snapshot[verdict.index]
    assert victim.in_flight == 0
    if any(not c.used for c in snapshot):
        assert not victim.used
    if not limits.evict:  # "refuse": only a silent one, only for a newcomer under its share
        assert verdict.never_used and _under_share(source, limits, snapshot)
    if verdict.never_used:
        counts = _counts(snapshot)
        assert victim.source != source and counts[victim.source] > counts.get(source, 0)
        # The heaviest source holding a silent one, and that source's oldest silent one.
        silent_sources = {c.source for c in snapshot if not c.used and c.source != source}
        assert counts[victim.source] == max(counts[s] for s in silent_sources)
        assert all(
            c.idle <= victim.idle for c in snapshot if c.source == victim.source and not c.used
        )


@given(SOURCES, LIMITS, st.lists(ANY_CONNECTION, max_size=14))
def test_a_newcomer_under_its_share_is_never_refused_while_a_heavier_source_is_silent(
    source: str, limits: ShareLimits, connections: list[OpenConnection]
) -> None:
    snapshot = _full(limits, connections)
    counts = _counts(snapshot)
    held = counts.get(source, 0)
    if limits.max_per_source and held >= limits.max_per_source:
        return
    heavier_silent = any(
        not c.used and c.source != source and counts[c.source] > held for c in snapshot
    )
    if heavier_silent and _under_share(source, limits, snapshot):
        assert not isinstance(admit_connection(source, limits, snapshot), Refuse)


# --------------------------------------------------------------------------- configuration


def test_the_default_has_no_cap_and_a_file_keeping_the_old_16_is_warned() -> None:
    lines = {"a": {"device": "/dev/null", "units": [1]}}
    assert build_config({"lines": lines}, "<test>").server.max_connections_per_source == 0
    for value, warned in ((16, True), (0, False), (15, False), (32, False)):
        raw = {"server": {"max_connections_per_source": value}, "lines": lines}
        warnings = config_warnings(build_config(raw, "<test>"))
        about = [w for w in warnings if w.startswith("server.max_connections_per_source")]
        assert bool(about) == warned, (value, warnings)
        if warned:
            assert "default is now 0" in about[0] and "one connection per device" in about[0]
