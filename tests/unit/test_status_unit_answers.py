"""The status unit's answers (agent mode), from poll blocks with literal times."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import PollConfig
from gateway.core.line.polling import AGE_NEVER, PollPlan
from gateway.core.status_unit import status_answer
from tests.helpers import h


def plan() -> PollPlan:
    """Three blocks: fresh (polled at 10.0, 2.34 s before ``NOW``), failing, never polled."""
    specs = [
        PollConfig(1, 3, 0, 10, 1.0, 3.0, "a", 1, 0),
        PollConfig(2, 3, 0, 2, 1.0, 3.0, "a", 2, 1),
        PollConfig(1, 4, 0, 4, 1.0, 3.0, "a", 1, 2),
    ]
    poll_plan = PollPlan(specs, 0.0)
    fresh, failing, _never = poll_plan.blocks
    fresh.answer, fresh.polled_at = bytes((3, 20)) + bytes(20), 10.0
    failing.answer, failing.polled_at, failing.failing = bytes((3, 4, 0, 1, 0, 2)), 5.0, True
    return poll_plan


NOW = 12.34


def test_two_registers_per_block_in_configuration_order() -> None:
    blocks = plan().blocks
    assert status_answer(h("03 0000 0006"), blocks, NOW) == h("03 0C 0017 0000 0049 0002 FFFF 0001")
    assert status_answer(h("04 0000 0006"), blocks, NOW)[2:] == h("0017 0000 0049 0002 FFFF 0001")
    assert status_answer(h("03 0003 0002"), blocks, NOW) == h("03 04 0002 FFFF")  # inside blocks
    assert status_answer(h("04 0005 0001"), blocks, NOW) == h("04 02 0001")  # the last one


def test_exceptions_past_the_registers_for_a_bad_count_and_other_functions() -> None:
    blocks = plan().blocks
    assert status_answer(h("03 0005 0002"), blocks, NOW) == h("83 02")
    assert status_answer(h("04 0006 0001"), blocks, NOW) == h("84 02")
    assert status_answer(h("03 FFFF 0001"), blocks, NOW) == h("83 02")
    assert status_answer(h("03 0000 0001"), [], NOW) == h("83 02")  # no block at all
    assert status_answer(h("03 0000 0000"), blocks, NOW) == h("83 03")
    assert status_answer(h("03 0000 007E"), blocks, NOW) == h("83 03")
    assert status_answer(h("03 0000"), blocks, NOW) == h("83 03")
    for request, refused in [
        ("06 0000 0001", "86 01"),
        ("10 0000 0001 02 0001", "90 01"),
        ("01 0000 0001", "81 01"),
        ("17 0000 0001 0000 0001 02 0000", "97 01"),
        ("2B 0E 01 00", "AB 01"),
    ]:
        assert status_answer(h(request), blocks, NOW) == h(refused)
    assert status_answer(b"", blocks, NOW) == h("80 01")


def test_the_age_saturates_at_65535() -> None:
    blocks = plan().blocks
    assert status_answer(h("03 0000 0002"), blocks, 10.0 + 6553.4) == h("03 04 FFFE 0001")
    assert status_answer(h("03 0000 0002"), blocks, 10.0 + 6553.5) == h("03 04 FFFF 0001")
    assert status_answer(h("03 0000 0002"), blocks, 1e9) == h("03 04 FFFF 0001")
    assert AGE_NEVER == 0xFFFF


@given(address=st.integers(0, 0xFFFF), count=st.integers(0, 0xFFFF), function=st.integers(0, 255))
def test_any_read_gets_an_answer_of_the_size_it_asked_or_an_exception(
    address: int, count: int, function: int
) -> None:
    pdu = bytes((function, address >> 8, address & 0xFF, count >> 8, count & 0xFF))
    answer = status_answer(pdu, plan().blocks, NOW)
    if answer[0] & 0x80:
        assert len(answer) == 2 and answer[1] in (1, 2, 3)
    else:
        assert function in (3, 4) and address + count <= 6
        assert answer[1] == 2 * count == len(answer) - 2


@pytest.mark.parametrize("count", [1, 2, 3, 4, 5, 6])
def test_every_sub_range_reads_the_same_values_as_the_whole(count: int) -> None:
    blocks = plan().blocks
    whole = status_answer(h("03 0000 0006"), blocks, NOW)[2:]
    for address in range(0, 7 - count):
        part = status_answer(bytes((3, 0, address, 0, count)), blocks, NOW)[2:]
        assert part == whole[2 * address : 2 * (address + count)]
