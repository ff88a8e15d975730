"""The audit record and its hash chain, with literal times: what is recorded, and that any
edited, removed or reordered line is found."""

from __future__ import annotations

import json

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.audit_record import (
    GENESIS,
    MAX_VALUES,
    AuditOutcome,
    Chain,
    Pending,
    Verifier,
    canonical,
    changed_keys,
    config_record,
    flatten,
    is_audited,
    link,
    opened_record,
    settle,
    timestamp,
    values_of,
)
from gateway.core.outcome import Outcome
from tests.helpers import h

T0 = 1_800_000_000.25


def test_reads_are_not_audited_and_everything_else_is() -> None:
    for read in ("03 0000 0001", "01 0000 0008", "04 0000 0001", "07", "18 0000",
                 "08 0000 1234", "08 000B 0000", "2B 0E 01 00"):  # fmt: skip
        assert not is_audited(h(read)), read
    for write in ("05 0001 FF00", "06 0001 0002", "10 0000 0001 02 0007", "0F 0000 0003 01 05",
                  "16 0000 00F2 0025", "17 0000 0001 0000 0001 02 0001", "08 0001 0000",
                  "08 0004 0000", "15 00", "41 01 02", "2B 0D 00", ""):  # fmt: skip
        assert is_audited(h(write)), write


def test_values_are_bounded_with_their_count() -> None:
    registers = h("10 0000 0020 40") + bytes(range(64))
    shown = values_of(registers)
    assert shown["count"] == 32 and len(shown["values"]) == MAX_VALUES
    assert shown["values"][:2] == [0x0001, 0x0203]
    assert values_of(h("05 0007 FF00")) == {"values": [1], "count": 1}
    assert values_of(h("06 0001 1234")) == {"values": [0x1234], "count": 1}
    assert values_of(h("0F 0000 0003 01 05")) == {"values": [1, 0, 1], "count": 3}
    assert values_of(h("16 0000 00F2 0025")) == {"values": [0xF2, 0x25], "count": 2}
    assert values_of(h("41 01 02")) == {"data": "0102", "count": 2}


def test_outcomes_of_the_lines_answers() -> None:
    assert settle(Outcome.OK, h("06 0001 0002"), True) == (AuditOutcome.ANSWERED, None)
    assert settle(Outcome.SLAVE_EXCEPTION, h("86 02"), True) == (AuditOutcome.EXCEPTION, 2)
    assert settle(Outcome.TARGET_FAILED, h("86 0B"), True) == (AuditOutcome.UNKNOWN, None)
    assert settle(Outcome.NO_ROUTE, h("86 0A"), True) == (AuditOutcome.UNKNOWN, None)
    assert settle(Outcome.BROADCAST, b"", True) == (AuditOutcome.BROADCAST, None)
    # Never on the wire: the write did nothing, and is not recorded.
    assert settle(Outcome.NO_ROUTE, h("86 0A"), False) is None
    assert settle(Outcome.TARGET_FAILED, h("86 0B"), False) is None
    assert settle(Outcome.BUSY, h("86 06"), False) is None
    assert settle(Outcome.DROPPED, b"", False) is None


def test_a_request_record_names_who_what_where_and_outcome() -> None:
    pending = Pending(T0, "tls", "127.0.0.1:5000", "operator", 11, h("10 0064 0002 04 0001 0002"),
                      "a", 1)  # fmt: skip
    record = pending.record(AuditOutcome.EXCEPTION, 2)
    assert record == {
        "event": "request", "time": "2027-01-15T08:00:00.250Z", "listener": "tls",
        "peer": "127.0.0.1:5000", "role": "operator", "unit": 11, "line": "a", "slave": 1,
        "function": 16, "function_name": "write_multiple_registers", "subfunction": None,
        "addresses": [[100, 101]], "values": [1, 2], "count": 2, "outcome": "exception",
        "code": 2,
    }  # fmt: skip
    assert timestamp(0.0) == "1970-01-01T00:00:00.000Z"


def test_configuration_changes_are_named_by_key() -> None:
    old = flatten({"server": {"max_pipeline": 16, "allow": []}, "lines": {"a": {"baud": 9600}}})
    new = flatten({"server": {"max_pipeline": 8, "allow": []}, "lines": {"b": {"baud": 9600}}})
    assert changed_keys(old, new) == ["lines.a.baud", "lines.b.baud", "server.max_pipeline"]
    assert flatten({"s": frozenset({3, 1, 2})}) == flatten({"s": frozenset({2, 3, 1})})
    record = config_record(T0, "reload", "/etc/g.toml", "ab" * 32, ["x"], accepted=True)
    assert record["result"] == "accepted" and record["changed"] == ["x"]


def sealed_log(records: int) -> list[str]:
    chain = Chain()
    lines = [chain.seal(opened_record(T0, GENESIS, "start"))]
    for n in range(records):
        pending = Pending(T0 + n, "tcp", "127.0.0.1:1", None, 1, h("06 0001") + n.to_bytes(2),
                          "a", 1)  # fmt: skip
        lines.append(chain.seal(pending.record(AuditOutcome.ANSWERED)))
    return lines


def verify(lines: list[str]) -> str | None:
    verifier = Verifier()
    for line in lines:
        if not verifier.check(line):
            return verifier.problem
    return None


def test_an_intact_log_verifies_and_each_line_is_canonical_json() -> None:
    lines = sealed_log(5)
    assert verify(lines) is None
    for line in lines:
        assert line.endswith("\n") and json.loads(line)["hash"]


def test_a_log_appended_to_after_a_restart_verifies() -> None:
    lines = sealed_log(2)
    head = json.loads(lines[-1])["hash"]
    chain = Chain(head)
    lines.append(chain.seal(opened_record(T0 + 9, head, "start")))
    assert verify(lines) is None
    assert json.loads(lines[-1])["prev"] == head
    # A forged restart: a new chain from the genesis, to hide what came before.
    body = canonical(opened_record(T0 + 9, GENESIS, "start"))
    lines.append(f'{body[:-1]},"hash":"{link(GENESIS, body)}"}}\n')
    assert "audit_opened does not follow" in (verify(lines) or "")


def test_an_opened_record_chains_from_the_head_it_is_sealed_after() -> None:
    chain = Chain("ab" * 32)
    assert json.loads(chain.seal(opened_record(T0, GENESIS, "reopen")))["prev"] == "ab" * 32


@given(st.data())
def test_any_edit_removal_or_swap_is_found(data: st.DataObject) -> None:
    lines = sealed_log(6)
    index = data.draw(st.integers(0, len(lines) - 1))
    how = data.draw(st.sampled_from(["edit", "remove", "swap", "duplicate"]))
    changed = list(lines)
    if how == "edit":
        record = json.loads(changed[index])
        record["time"] = "2000-01-01T00:00:00.000Z"
        changed[index] = json.dumps(record) + "\n"
    elif how == "remove":
        if index == len(lines) - 1:
            return  # a cut at the end leaves an intact chain: docs/audit.md says so
        del changed[index]
    elif how == "swap":
        other = (index + 1) % len(lines)
        changed[index], changed[other] = changed[other], changed[index]
    else:
        changed.insert(index, changed[index])
    problem = verify(changed)
    assert problem is not None and problem.startswith("line "), (how, index)


def test_the_first_bad_line_is_named() -> None:
    lines = sealed_log(4)
    lines[3] = lines[3].replace('"values":[2]', '"values":[7]')
    assert (verify(lines) or "").startswith("line 4: hash mismatch")
    assert (verify(sealed_log(4)[1:]) or "").startswith("line 1: the file does not begin")
    assert (verify(["{}\n"]) or "").startswith("line 1: not a sealed")
