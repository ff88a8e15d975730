"""Cuts anywhere in an audit file, its head included, fail verification (literal times).

The writer marks every ``audit_opened`` record with ``starts_file`` (the file was
empty when opened) and ``records_before`` (what the file held); these tests build
files the way the writer does: a start, writes, a reopen of the same file, writes.
"""

from __future__ import annotations

import json

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.audit_record import (
    GENESIS,
    AuditOutcome,
    Chain,
    Pending,
    Record,
    Verifier,
    opened_record,
)

T0 = 1_800_000_000.25


def opened(reason: str, before: int, now: float = T0) -> Record:
    return {**opened_record(now, GENESIS, reason), "starts_file": before == 0,
            "records_before": before}  # fmt: skip


def write(n: int) -> Record:
    pdu = bytes.fromhex("06 0001") + n.to_bytes(2)
    return Pending(T0 + n, "tcp", "127.0.0.1:1", None, 1, pdu, "a", 1).record(AuditOutcome.ANSWERED)


def written_file(chain: Chain, writes: tuple[int, ...] = (3, 3)) -> list[str]:
    """A file as the writer makes it: a start, then a reopen of the same file per batch."""
    lines: list[str] = []
    for batch, count in enumerate(writes):
        lines.append(chain.seal(opened("start" if batch == 0 else "reopen", len(lines))))
        lines += [chain.seal(write(10 * batch + n)) for n in range(count)]
    return lines


def verify(*files: list[str]) -> str | None:
    verifier = Verifier()
    for lines in files:
        verifier.start_file()
        for line in lines:
            if not verifier.check(line):
                return verifier.problem
    return None


def test_a_file_as_written_verifies_alone_and_a_rotated_pair_in_order() -> None:
    chain = Chain()
    first = written_file(chain)
    assert verify(first) is None
    second = written_file(chain, (2,))  # after a rotation: a new file, chained on
    assert json.loads(second[0])["starts_file"] is True
    assert json.loads(second[0])["prev"] == json.loads(first[-1])["hash"]
    assert verify(second) is None  # a file that starts a file verifies alone
    assert verify(first, second) is None
    assert verify(first + second) is None  # concatenated into one file, too


def test_cutting_the_head_up_to_a_reopen_fails() -> None:
    lines = written_file(Chain())
    reopen = next(n for n, line in enumerate(lines) if '"reason":"reopen"' in line)
    problem = verify(lines[reopen:])
    assert problem is not None and problem.startswith(
        "line 1: the file's first record continues a file that held 4 records"
    )


def test_cutting_records_just_before_a_reopen_fails_even_with_the_chain_mended() -> None:
    # Someone who removes the writes before a reopen and re-seals everything after
    # them from the start (no secret key) still leaves the reopen's count.
    chain = Chain()
    lines = [chain.seal(opened("start", 0)), chain.seal(write(1))]
    lines.append(chain.seal(opened("reopen", 4)))  # the count the writer had: 4
    problem = verify(lines)
    assert problem is not None and "counts 4 records before it" in problem


@given(st.integers(0, 8), st.integers(1, 8))
def test_any_cut_of_the_head_or_the_middle_is_found(start: int, length: int) -> None:
    lines = written_file(Chain(), (3, 2, 2))
    cut = lines[:start] + lines[start + length :]
    if start == 0 and length < len(lines):
        assert verify(cut) is not None, (start, length)  # the head
    elif start > 0 and start + length < len(lines):
        assert verify(cut) is not None, (start, length)  # the middle
    # A cut reaching the end leaves an intact chain: docs/audit.md says so.


def test_records_written_before_the_count_existed_still_verify() -> None:
    chain = Chain()
    lines = [chain.seal(opened_record(T0, GENESIS, "start")), chain.seal(write(1))]
    lines.append(chain.seal(opened_record(T0, GENESIS, "reopen")))
    assert verify(lines) is None
