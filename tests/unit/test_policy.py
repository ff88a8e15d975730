"""The authorization core: classification, decisions, the role extension, the lint."""

from __future__ import annotations

import ipaddress

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import ConfigError, build_config, policy_warnings
from gateway.core.policy import (
    Access,
    DenyReason,
    Operation,
    Policy,
    Principal,
    Rule,
    classify,
    decode_role,
    lint,
    merge_ranges,
)
from gateway.core.routes import Target
from tests.helpers import h


def net(text: str) -> ipaddress.IPv4Network | ipaddress.IPv6Network:
    return ipaddress.ip_network(text)


OPERATOR = Principal(ipaddress.ip_address("10.0.0.5"), "operator")
VIEWER = Principal(ipaddress.ip_address("10.0.0.6"), "viewer")
NULL = Principal(ipaddress.ip_address("10.0.0.7"), None)


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        ("03 0064 000A", Operation(3, None, Access.READ, ((100, 109),))),
        ("01 0000 07D0", Operation(1, None, Access.READ, ((0, 1999),))),
        ("06 0005 1234", Operation(6, None, Access.WRITE, ((5, 5),))),
        ("05 0007 FF00", Operation(5, None, Access.WRITE, ((7, 7),))),
        ("10 0010 0002 04 00010002", Operation(16, None, Access.WRITE, ((16, 17),))),
        ("16 0003 00F2 0025", Operation(22, None, Access.WRITE, ((3, 3),))),
        ("17 0000 0002 0100 0001 02 0007", Operation(23, None, Access.READ_WRITE,
                                                    ((0, 1), (256, 256)))),
        ("18 04DE", Operation(24, None, Access.READ, ((1246, 1246),))),
        ("08 0000 A537", Operation(8, 0, Access.READ)),
        ("08 0004 0000", Operation(8, 4, Access.WRITE)),
        ("08 000A 0000", Operation(8, 10, Access.WRITE)),
        ("08 000B 0000", Operation(8, 11, Access.READ)),
        ("2B 0E 01 00", Operation(43, 14, Access.READ)),
        ("2B 0D 00", Operation(43, 13, Access.WRITE)),
        ("07", Operation(7, None, Access.READ)),
        ("11", Operation(17, None, Access.READ)),
        ("41 0102", Operation(0x41, None, Access.WRITE)),  # user-defined: effect unknown
        ("03 00", Operation(3, None, Access.READ, ())),  # short: no range to grant
        ("03 FFFF 0010", Operation(3, None, Access.READ, ((65535, 65535),))),
        ("", Operation(0, None, Access.WRITE)),
    ],
)  # fmt: skip
def test_classify(pdu: str, expected: Operation) -> None:
    assert classify(h(pdu)) == expected


def test_merge_ranges_joins_adjacent_and_overlapping() -> None:
    assert merge_ranges([(10, 19), (0, 9), (30, 40), (35, 50)]) == ((0, 19), (30, 50))


def test_a_listener_without_rules_serves_everything_but_listen_only_mode() -> None:
    policy = Policy()
    assert policy.open
    assert policy.decide(NULL, 1, h("06 0000 0001")).allowed
    assert policy.decide(NULL, 0, h("06 0000 0001")).allowed  # broadcast, as before rules
    assert policy.decide(NULL, 1, h("08 0004 0000")).denied is DenyReason.LISTEN_ONLY_MODE


def test_read_only_refuses_every_write_whatever_the_rules() -> None:
    everything = Policy((Rule(key="all"),), read_only=True)
    assert everything.decide(OPERATOR, 1, h("03 0000 0001")).allowed
    for pdu in ("06 0000 0001", "17 0000 0001 0000 0001 02 0000", "41", "08 0001 0000"):
        assert everything.decide(OPERATOR, 1, h(pdu)).denied is DenyReason.READ_ONLY
    assert Policy(read_only=True).decide(NULL, 1, h("10 0000 0001 02 0000")).denied is (
        DenyReason.READ_ONLY
    )


def test_a_tls_listener_without_rules_refuses_the_null_role() -> None:
    policy = Policy(tls=True)
    assert not policy.open
    assert policy.decide(OPERATOR, 1, h("06 0000 0001")).allowed
    assert policy.decide(NULL, 1, h("03 0000 0001")).denied is DenyReason.NULL_ROLE


PLANT = Policy(
    (
        Rule(key="r0", role="operator", units=frozenset({1}),
             functions=frozenset({(3, None), (6, None), (16, None)}), addresses=((0, 99),)),
        Rule(key="r1", role="viewer", units=frozenset({1, 2}), access=Access.READ),
        Rule(key="r2", role="operator", units=frozenset({0}), functions=frozenset({(6, None)})),
        Rule(key="r3", sources=(net("10.0.0.0/29"),), units=frozenset({3}), access=Access.READ),
        Rule(key="r4", role="maintenance", functions=frozenset({(8, 4)})),
    ),
    tls=True,
)  # fmt: skip


@pytest.mark.parametrize(
    ("principal", "unit", "pdu", "rule"),
    [
        (OPERATOR, 1, "03 0000 000A", "r0"),
        (OPERATOR, 1, "03 005A 000A", "r0"),  # 90..99: the last address of the range
        (OPERATOR, 1, "03 005B 000A", None),  # 91..100: one address outside
        (OPERATOR, 1, "06 0063 0001", "r0"),
        (OPERATOR, 1, "06 0064 0001", None),
        (OPERATOR, 1, "05 0000 FF00", None),  # function not named
        (OPERATOR, 2, "03 0000 0001", None),  # unit not named
        (OPERATOR, 0, "06 0000 0001", "r2"),  # broadcast: named explicitly
        (OPERATOR, 0, "10 0000 0001 02 0000", None),
        (OPERATOR, 3, "03 0000 0001", "r3"),  # by source, whatever the role
        (VIEWER, 1, "03 005B 000A", "r1"),
        (VIEWER, 2, "04 0000 0001", "r1"),
        (VIEWER, 1, "06 0000 0001", None),
        (VIEWER, 1, "17 0000 0001 0000 0001 02 0000", None),  # reads and writes: needs write
        (VIEWER, 1, "08 0000 1234", "r1"),  # echo: a read
        (VIEWER, 1, "08 0004 0000", None),
        (VIEWER, 0, "06 0000 0001", None),  # broadcast is never implied
        (VIEWER, 1, "41", None),  # unknown function: a write
        (NULL, 1, "03 0000 0001", None),
        (NULL, 3, "03 0000 0001", "r3"),
        (Principal(ipaddress.ip_address("10.0.0.9")), 3, "03 0000 0001", None),
        (Principal(None, "maintenance"), 7, "08 0004 0000", "r4"),
    ],
)
def test_rules_only_grant(principal: Principal, unit: int, pdu: str, rule: str | None) -> None:
    decision = PLANT.decide(principal, unit, h(pdu))
    assert (decision.rule.key if decision.rule else None) == rule
    assert decision.allowed is (rule is not None)


def test_listen_only_mode_needs_a_rule_that_names_it() -> None:
    all_diagnostics = Policy((Rule(key="d", functions=frozenset({(8, None)})),))
    assert all_diagnostics.decide(NULL, 1, h("08 0000 0000")).allowed
    assert all_diagnostics.decide(NULL, 1, h("08 0004 0000")).denied is DenyReason.LISTEN_ONLY_MODE
    assert Policy((Rule(key="all"),)).decide(NULL, 1, h("08 0004 0000")).denied is (
        DenyReason.LISTEN_ONLY_MODE
    )


def test_role_labels_are_bounded() -> None:
    assert PLANT.role_label("operator") == "operator"
    assert PLANT.role_label("intruder-1234") == "other"
    assert PLANT.role_label(None) == "none"


@pytest.mark.parametrize(
    ("value", "role"),
    [
        ("0C 08 6F70657261746F72", "operator"),
        ("0C 81 08 6F70657261746F72", "operator"),  # long-form length, still one string
        ("02 01 05", None),  # INTEGER
        ("13 08 6F70657261746F72", None),  # PrintableString
        ("0C 09 6F70657261746F72", None),  # length past the end
        ("0C 07 6F70657261746F72", None),  # trailing byte
        ("0C 02 C328", None),  # invalid UTF-8
        ("0C 00", None),  # empty
        ("0C", None),
        ("", None),
        ("0C 80", None),  # indefinite length
    ],
)
def test_decode_role(value: str, role: str | None) -> None:
    assert decode_role(h(value)) == role


@given(st.binary(max_size=40))
def test_decode_role_never_raises(value: bytes) -> None:
    decode_role(value)


principals = st.builds(
    Principal,
    st.sampled_from([None, ipaddress.ip_address("10.0.0.5"), ipaddress.ip_address("::1")]),
    st.sampled_from([None, "operator", "viewer", "x"]),
)
rules = st.builds(
    Rule,
    key=st.just("r"),
    role=st.sampled_from([None, "operator", "viewer"]),
    sources=st.sampled_from([(), (net("10.0.0.0/24"),), (net("::1/128"),)]),
    units=st.one_of(st.none(), st.frozensets(st.integers(0, 4), max_size=3)),
    functions=st.one_of(
        st.none(),
        st.frozensets(st.sampled_from([(3, None), (6, None), (8, None), (8, 4), (23, None)])),
    ),
    addresses=st.one_of(st.none(), st.lists(st.tuples(st.integers(0, 50), st.integers(0, 50))
                        .map(sorted).map(tuple), max_size=3).map(merge_ranges)),  # type: ignore[arg-type]
    access=st.sampled_from([Access.READ, Access.WRITE, Access.READ_WRITE]),
)  # fmt: skip
pdus = st.one_of(
    st.binary(max_size=12),
    st.tuples(st.sampled_from([1, 3, 5, 6, 8, 15, 16, 22, 23]), st.binary(min_size=4, max_size=10))
    .map(lambda t: bytes([t[0]]) + t[1]),
)  # fmt: skip


@given(st.lists(rules, max_size=5), principals, st.integers(0, 5), pdus, st.booleans())
def test_decisions_are_total_and_independent_of_rule_order(
    rule_list: list[Rule], principal: Principal, unit: int, pdu: bytes, tls: bool
) -> None:
    forward = Policy(tuple(rule_list), tls=tls).decide(principal, unit, pdu)
    backward = Policy(tuple(reversed(rule_list)), tls=tls).decide(principal, unit, pdu)
    assert forward.allowed == backward.allowed


@given(st.lists(rules, max_size=4), rules, principals, st.integers(0, 5), pdus)
def test_a_further_rule_never_takes_a_right_away(
    rule_list: list[Rule], extra: Rule, principal: Principal, unit: int, pdu: bytes
) -> None:
    before = Policy(tuple(rule_list)).decide(principal, unit, pdu)
    after = Policy((*rule_list, extra)).decide(principal, unit, pdu)
    assert after.allowed or not before.allowed


def test_lint_finds_rules_that_never_match() -> None:
    rules = (
        Rule(key="p.rules[0]", role="operator"),
        Rule(key="p.rules[1]", sources=(net("192.168.9.0/24"),)),
        Rule(key="p.rules[2]", units=frozenset({77})),
        Rule(key="p.rules[3]", functions=frozenset({(3, None)}), access=Access.WRITE),
        Rule(key="p.rules[4]", functions=frozenset({(8, None)}), addresses=((0, 9),)),
        Rule(key="p.rules[5]", sources=(net("10.0.0.0/24"),), units=frozenset({1})),
        Rule(key="p.rules[6]", sources=(net("10.0.0.0/25"),), units=frozenset({1}),
             access=Access.READ),
        Rule(key="p.rules[7]", access=Access.WRITE),
    )  # fmt: skip
    warnings = lint(
        rules, listener="plain", tls=False, read_only=True, allow=(net("10.0.0.0/8"),),
        routes={1: Target("a", 1), 2: Target("a", 2)},
    )  # fmt: skip
    text = "\n".join(warnings)
    assert "p.rules[0] (listener 'plain'): role 'operator' never matches on a plain tcp" in text
    assert "p.rules[1] (listener 'plain'): source 192.168.9.0/24 is outside" in text
    assert "p.rules[2] (listener 'plain'): none of its units is routed" in text
    assert "p.rules[3] (listener 'plain'): access WRITE covers none of its functions" in text
    assert "p.rules[4] (listener 'plain'): addresses is set but none of its functions" in text
    assert "p.rules[6] (listener 'plain'): adds nothing to p.rules[5]" in text
    assert "p.rules[7] (listener 'plain'): grants only writes, which the read-only" in text
    assert not [w for w in warnings if w.startswith("p.rules[5]")]
    assert lint(PLANT.rules or (), listener="s", tls=True, read_only=False, allow=(),
                routes={u: Target("a", u) for u in (1, 2, 3)}) == []  # fmt: skip


# --------------------------------------------------------------------------- rules follow the slave

#: Line a: slaves 1 and 2, each under two unit ids (2 and 12 reach slave 2); line b: slave 1.
ROUTES = {1: Target("a", 1), 11: Target("a", 1), 2: Target("a", 2), 12: Target("a", 2),
          3: Target("b", 1)}  # fmt: skip
READ = h("03 0000 0001")
WRITE = h("06 0000 0001")


def routed(policy: Policy, unit: int, pdu: bytes, who: Principal = NULL) -> bool:
    """Whether ``policy`` serves ``pdu`` sent to ``unit``, routed as ``ROUTES`` says."""
    return policy.decide(who, unit, pdu, ROUTES.get(unit)).allowed


def test_an_alias_inherits_the_rules_of_its_slave() -> None:
    policy = Policy((Rule(key="r", units=frozenset({2}), access=Access.READ),), routes=ROUTES)
    assert routed(policy, 2, READ) and routed(policy, 12, READ)  # 12 reaches slave 2 too
    assert not routed(policy, 12, WRITE)
    assert not routed(policy, 1, READ) and not routed(policy, 11, READ)
    named_by_alias = Policy((Rule(key="r", units=frozenset({12})),), routes=ROUTES)
    assert routed(named_by_alias, 2, WRITE)  # the rule names the slave, by either unit id


def test_an_unrouted_unit_is_matched_by_the_unit_sent() -> None:
    policy = Policy((Rule(key="r", units=frozenset({2, 77})),), routes=ROUTES)
    assert policy.decide(NULL, 77, READ, None).allowed
    assert not policy.decide(NULL, 78, READ, None).allowed


def test_line_and_slave_restrict_a_rule_to_routed_targets() -> None:
    on_a = Policy((Rule(key="a", lines=frozenset({"a"})),), routes=ROUTES)
    assert routed(on_a, 1, WRITE) and routed(on_a, 12, WRITE)
    assert not routed(on_a, 3, READ)  # line b
    assert not on_a.decide(NULL, 77, READ, None).allowed  # unrouted: no line
    assert not on_a.decide(NULL, 0, WRITE, None).allowed  # broadcast: no single line
    slave_1 = Policy((Rule(key="s", lines=frozenset({"a"}), slaves=frozenset({1})),), routes=ROUTES)
    assert routed(slave_1, 1, WRITE) and routed(slave_1, 11, WRITE)
    assert not routed(slave_1, 2, READ) and not routed(slave_1, 12, READ)
    any_line = Policy((Rule(key="s", slaves=frozenset({1})),), routes=ROUTES)
    assert routed(any_line, 3, READ) and routed(any_line, 11, READ)
    assert not routed(any_line, 2, READ)
    both = Policy((Rule(key="u", units=frozenset({2}), lines=frozenset({"b"})),), routes=ROUTES)
    assert not routed(both, 2, READ) and not routed(both, 3, READ)  # all dimensions must hold


def test_without_routes_a_rule_matches_the_unit_sent_as_before() -> None:
    policy = Policy((Rule(key="r", units=frozenset({2})),))
    assert policy.decide(NULL, 2, READ, Target("a", 2)).allowed
    assert not policy.decide(NULL, 12, READ, Target("a", 2)).allowed
    by_line = Policy((Rule(key="l", units=frozenset({2}), lines=frozenset({"a"})),))
    assert by_line.decide(NULL, 2, READ, Target("a", 2)).allowed


some_targets = st.builds(Target, st.sampled_from(["a", "b"]), st.integers(1, 3))
route_tables = st.dictionaries(st.integers(1, 5), some_targets, max_size=5)
rules_with_targets = st.builds(
    Rule,
    key=st.just("r"),
    units=st.one_of(st.none(), st.frozensets(st.integers(0, 6), max_size=3)),
    lines=st.one_of(st.none(), st.frozensets(st.sampled_from(["a", "b"]), max_size=2)),
    slaves=st.one_of(st.none(), st.frozensets(st.integers(1, 3), max_size=2)),
    access=st.sampled_from([Access.READ, Access.WRITE, Access.READ_WRITE]),
)


@given(st.lists(rules_with_targets, max_size=4), route_tables, st.integers(0, 6), pdus)
def test_every_unit_id_of_a_slave_has_the_same_rights(
    rule_list: list[Rule], routes: dict[int, Target], unit: int, pdu: bytes
) -> None:
    policy = Policy(tuple(rule_list), routes=routes)
    target = routes.get(unit)
    decision = policy.decide(NULL, unit, pdu, target).allowed
    for alias, other in routes.items():
        if other == target:
            assert policy.decide(NULL, alias, pdu, other).allowed == decision


@given(st.lists(rules_with_targets, max_size=4), rules_with_targets, route_tables,
       st.integers(0, 6), pdus)  # fmt: skip
def test_a_further_rule_never_takes_a_right_away_with_routes(
    rule_list: list[Rule], extra: Rule, routes: dict[int, Target], unit: int, pdu: bytes
) -> None:
    target = routes.get(unit)
    before = Policy(tuple(rule_list), routes=routes).decide(NULL, unit, pdu, target)
    after = Policy((*rule_list, extra), routes=routes).decide(NULL, unit, pdu, target)
    assert after.allowed or not before.allowed


def test_lint_says_when_a_rule_names_only_some_unit_ids_of_a_slave() -> None:
    rules = (
        Rule(key="p.rules[0]", units=frozenset({1, 12}), access=Access.READ),
        Rule(key="p.rules[1]", units=frozenset({11, 2}), access=Access.READ),  # the same slaves
        Rule(key="p.rules[2]", lines=frozenset({"c"})),
        Rule(key="p.rules[3]", units=frozenset({1, 11, 2, 12}), access=Access.WRITE),
    )
    warnings = lint(rules, listener="l", tls=False, read_only=False, allow=(), routes=ROUTES)
    text = "\n".join(warnings)
    assert (
        "p.rules[0] (listener 'l'): line 'a' slave 2 is reached by units 2, 12, and the rule "
        "names only unit 12: rules follow the slave" in text
    )
    assert "p.rules[0] (listener 'l'): line 'a' slave 1 is reached by units 1, 11" in text
    assert "p.rules[1] (listener 'l'): adds nothing to p.rules[0]" in text
    assert "p.rules[2] (listener 'l'): no route reaches its line and slave" in text
    assert not [w for w in warnings if w.startswith("p.rules[3]")]


def _configured(rules: list[dict[str, object]]) -> dict[str, object]:
    return {
        "lines": {"a": {"device": "/dev/ttyA", "units": [1, 2]},
                  "b": {"device": "/dev/ttyB", "units": [3]}},
        "routes": [{"unit": 12, "line": "a", "slave": 2}],
        "server": {"policy": "p"},
        "policies": {"p": {"rules": rules}},
    }  # fmt: skip


def test_rules_name_line_and_slave_in_the_configuration() -> None:
    built = build_config(_configured([{"line": "a", "slave": [1, "2-3"]}, {"line": ["a", "b"]}]))
    first, second = built.policies["p"]
    assert (first.lines, first.slaves) == (frozenset({"a"}), frozenset({1, 2, 3}))
    assert (second.lines, second.slaves) == (frozenset({"a", "b"}), None)
    with pytest.raises(ConfigError) as raised:
        build_config(_configured([{"line": 7, "slave": [0]}]))
    text = str(raised.value)
    assert "policies.p.rules[0].line: write a line name or a list of them" in text
    assert "policies.p.rules[0].slave: 0 outside 1..247" in text


def test_check_config_names_the_rules_an_alias_widens() -> None:
    built = build_config(_configured([{"units": [12], "access": "read"}, {"line": "c"}]))
    text = "\n".join(policy_warnings(built))
    assert "line 'a' slave 2 is reached by units 2, 12, and the rule names only unit 12" in text
    assert "policies.p.rules[1] (listener 'tcp'): no route reaches its line and slave" in text
