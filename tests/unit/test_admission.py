"""Admission: the one decision every listener executes, with literal inputs."""

from __future__ import annotations

import ipaddress

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.admission import Admission, Admitter, AnswerLocally, Broadcast, Submit
from gateway.core.errors import ExceptionCode
from gateway.core.outcome import Outcome
from gateway.core.policy import Access, DenyReason, Policy, Principal, Rule
from gateway.core.routes import Target
from tests.helpers import h

#: Line a: slave 1 (unit 1) and slave 2 (units 2 and its alias 12); line b takes broadcasts.
ROUTES = {1: Target("a", 1), 2: Target("a", 2), 12: Target("a", 2)}
ADMITTER = Admitter.of(ROUTES, ["a"])
ANYONE = Principal(ipaddress.ip_address("10.0.0.5"))
OPEN = Policy(routes=ROUTES)
#: Slave 1 fully, slave 2 read only (named by unit 2 only), broadcasts of FC 6.
RULES = Policy(
    (
        Rule(key="r0", units=frozenset({1})),
        Rule(key="r1", units=frozenset({2}), access=Access.READ),
        Rule(key="r2", units=frozenset({0}), functions=frozenset({(6, None)})),
    ),
    routes=ROUTES,
    refuse_functions=frozenset({0x11}),
)
READ = h("03 0000 0001")
WRITE = h("06 0000 0001")


def answer(code: ExceptionCode, outcome: Outcome, routed: bool = True) -> tuple[object, ...]:
    return code, outcome, routed


def summary(result: Admission) -> object:
    if isinstance(result, AnswerLocally):
        return result.code, result.outcome, result.routed
    return result


@pytest.mark.parametrize(
    ("policy", "unit", "pdu", "expected"),
    [
        (OPEN, 1, READ, Submit(Target("a", 1))),
        (OPEN, 12, READ, Submit(Target("a", 2))),
        (OPEN, 0, WRITE, Broadcast(("a",))),
        (OPEN, 9, READ, answer(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE, False)),
        (OPEN, 1, h("08 0000 A537"), Submit(Target("a", 1))),  # echo
        (OPEN, 1, h("08 0004 0000"), answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED)),
        (OPEN, 1, h("2B 0E 01 00"), Submit(Target("a", 1))),
        (OPEN, 1, h("41 0102"), Submit(Target("a", 1))),  # a user function: the slave decides
        (OPEN, 0, READ, answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED)),
        (OPEN, 1, h("03 0000 0000"), answer(ExceptionCode.ILLEGAL_DATA_VALUE, Outcome.REJECTED)),
        (OPEN, 1, b"", answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED)),
        (RULES, 1, WRITE, Submit(Target("a", 1))),
        (RULES, 2, READ, Submit(Target("a", 2))),
        (RULES, 12, READ, Submit(Target("a", 2))),  # the alias inherits unit 2's rule
        (RULES, 12, WRITE, answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED)),
        (RULES, 2, WRITE, answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED)),
        (RULES, 0, WRITE, Broadcast(("a",))),
        (
            RULES,
            0,
            h("10 0000 0001 02 0000"),
            answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED),
        ),
        (RULES, 1, h("11"), answer(ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED)),  # refused
    ],
)
def test_each_request_gets_one_typed_result(
    policy: Policy, unit: int, pdu: bytes, expected: object
) -> None:
    assert summary(ADMITTER.admit(ANYONE, unit, pdu, policy)) == expected


def test_denied_beats_unrouted_so_a_master_learns_nothing() -> None:
    """A unit no rule names gets 0x01, routed or not: its existence does not show."""
    for unit in (12, 9):  # 12 is routed (to slave 2, read only), 9 is not
        result = ADMITTER.admit(ANYONE, unit, WRITE, RULES)
        assert isinstance(result, AnswerLocally)
        assert (result.code, result.outcome) == (ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED)
        assert result.denied is DenyReason.NO_RULE
        assert result.routed is (unit == 12)  # for the serial slave's silence only


def test_the_order_of_the_checks() -> None:
    refusing = Policy(routes=ROUTES, refuse_functions=frozenset({3}))
    # denied beats refused, invalid and unrouted: FC 8/4 malformed beyond the subfunction
    denied = ADMITTER.admit(ANYONE, 9, h("08 0004"), OPEN)
    assert summary(denied) == (ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED, False)
    # refused beats invalid: a malformed read of a refused function is refused
    refused = ADMITTER.admit(ANYONE, 1, h("03 00"), refusing)
    assert isinstance(refused, AnswerLocally) and refused.outcome is Outcome.REJECTED
    assert refused.code is ExceptionCode.ILLEGAL_FUNCTION
    assert "refuse_functions" in refused.reason
    # refused beats unrouted
    assert summary(ADMITTER.admit(ANYONE, 9, READ, refusing)) == (
        ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED, False,
    )  # fmt: skip
    # the broadcast rule beats invalid: a malformed read to unit 0
    not_a_write = ADMITTER.admit(ANYONE, 0, h("03 00"), OPEN)
    assert summary(not_a_write) == (ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED, True)
    # invalid beats unrouted
    assert summary(ADMITTER.admit(ANYONE, 9, h("03 0000 0000"), OPEN)) == (
        ExceptionCode.ILLEGAL_DATA_VALUE, Outcome.REJECTED, False,
    )  # fmt: skip


def test_an_unrouted_unit_is_authorized_by_the_unit_sent() -> None:
    naming_9 = Policy((Rule(key="r", units=frozenset({9})),), routes=ROUTES)
    assert summary(ADMITTER.admit(ANYONE, 9, READ, naming_9)) == (
        ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE, False,
    )  # fmt: skip
    assert summary(ADMITTER.admit(ANYONE, 8, READ, naming_9))[1] is Outcome.DENIED  # type: ignore[index]


def test_a_listener_serving_some_units_treats_the_others_as_unrouted() -> None:
    serves = frozenset({1})
    assert ADMITTER.admit(ANYONE, 1, READ, OPEN, serves) == Submit(Target("a", 1))
    assert summary(ADMITTER.admit(ANYONE, 2, READ, OPEN, serves)) == (
        ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE, False,
    )  # fmt: skip
    assert ADMITTER.admit(ANYONE, 0, WRITE, OPEN, serves) == Broadcast(("a",))


def test_no_broadcast_line_answers_0x0a() -> None:
    result = Admitter.of(ROUTES).admit(ANYONE, 0, WRITE, OPEN)
    assert summary(result) == (ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE, True)


def test_a_read_only_or_tls_listener_asks_the_policy_for_every_request() -> None:
    read_only = Policy(read_only=True, routes=ROUTES)
    assert ADMITTER.admit(ANYONE, 1, READ, read_only) == Submit(Target("a", 1))
    assert summary(ADMITTER.admit(ANYONE, 1, WRITE, read_only))[1] is Outcome.DENIED  # type: ignore[index]
    tls = Policy(tls=True, routes=ROUTES)
    assert summary(ADMITTER.admit(Principal(None, None), 1, READ, tls))[1] is Outcome.DENIED  # type: ignore[index]
    assert ADMITTER.admit(Principal(None, "viewer"), 1, READ, tls) == Submit(Target("a", 1))


# --------------------------------------------------------------------------- properties

principals = st.builds(
    Principal,
    st.sampled_from([None, ipaddress.ip_address("10.0.0.5")]),
    st.sampled_from([None, "operator"]),
)
rules = st.builds(
    Rule,
    key=st.just("r"),
    role=st.sampled_from([None, "operator"]),
    units=st.one_of(st.none(), st.frozensets(st.sampled_from([0, 1, 2, 9, 12]), max_size=3)),
    lines=st.one_of(st.none(), st.just(frozenset({"a"}))),
    functions=st.one_of(
        st.none(), st.frozensets(st.sampled_from([(3, None), (6, None), (8, None), (8, 4)]))
    ),
    access=st.sampled_from([Access.READ, Access.WRITE, Access.READ_WRITE]),
)
policies = st.builds(
    Policy,
    st.one_of(st.none(), st.lists(rules, max_size=4).map(tuple)),
    st.booleans(),
    st.booleans(),
    st.just(ROUTES),
    st.frozensets(st.sampled_from([3, 6, 8, 0x11]), max_size=2),
)
pdus = st.one_of(
    st.binary(max_size=12),
    st.tuples(st.sampled_from([3, 5, 6, 8, 16, 17, 43, 0x41]), st.binary(max_size=8)).map(
        lambda t: bytes([t[0]]) + t[1]
    ),
)
units = st.sampled_from([0, 1, 2, 9, 12, 255])


@given(principals, units, pdus, policies)
def test_nothing_denied_refused_or_invalid_reaches_a_line(
    principal: Principal, unit: int, pdu: bytes, policy: Policy
) -> None:
    result = ADMITTER.admit(principal, unit, pdu, policy)  # total: never raises
    if isinstance(result, Submit | Broadcast):
        assert policy.decide(principal, unit, pdu, ROUTES.get(unit)).allowed
        assert pdu[0] not in policy.refuse_functions
    else:
        assert result.routed == (unit in ROUTES or unit == 0)


@given(principals, pdus, policies)
def test_an_alias_gets_what_its_slave_gets(
    principal: Principal, pdu: bytes, policy: Policy
) -> None:
    """Units 2 and 12 reach one slave: every policy treats them alike."""
    first = summary(ADMITTER.admit(principal, 2, pdu, policy))
    assert summary(ADMITTER.admit(principal, 12, pdu, policy)) == first


def test_the_table_gives_each_slave_the_lowest_unit_that_reaches_it() -> None:
    """What a standby of a pair sends the active: the table's unit for the routed slave,
    the same whichever alias the master used."""
    table = Admitter.of({12: Target("a", 2), 2: Target("a", 2), 1: Target("a", 1)}).table
    assert table.units == {Target("a", 1): 1, Target("a", 2): 2}
    assert table.units.get(("a", 2)) == 2 and table.units.get(("b", 2)) is None


def test_a_unit_the_gateway_answers_itself_is_granted_by_its_unit_id_only() -> None:
    """The status unit goes to a line of its own, but the policy sees it unrouted: a rule
    that names slave 100 (on any line) does not reach status unit 100; one listing unit 100
    does."""
    own = Admitter.of(ROUTES, ["a"], {100: Target("status", 100)})
    assert own.admit(ANYONE, 100, READ, OPEN) == Submit(Target("status", 100))
    assert own.table.lookup(100) is None  # not a route of the table a pair forwards by
    by_slave = Policy((Rule(key="r", slaves=frozenset({1, 100})),), routes=ROUTES)
    assert own.admit(ANYONE, 1, READ, by_slave) == Submit(Target("a", 1))
    denied = summary(own.admit(ANYONE, 100, READ, by_slave))
    assert denied == (ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED, True)
    naming = Policy((Rule(key="r", units=frozenset({100}), access=Access.READ),), routes=ROUTES)
    assert own.admit(ANYONE, 100, READ, naming) == Submit(Target("status", 100))
    assert summary(own.admit(ANYONE, 100, WRITE, naming))[1] is Outcome.DENIED  # type: ignore[index]
