"""The instruction count's arithmetic: one transaction's cost from two runs of one server."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.instruction_scenarios import instructions_in, per_transaction


def test_start_up_cancels_out() -> None:
    # 1.2 G to start and stop, 70 k per transaction: 600 and 3,000 transactions.
    short = (600, 1_200_000_000 + 600 * 70_000)
    long = (3_000, 1_200_000_000 + 3_000 * 70_000)
    assert per_transaction(short, long) == 70_000


@given(
    start=st.integers(0, 10**10),
    cost=st.integers(1, 10**6),
    first=st.integers(0, 10**5),
    more=st.integers(1, 10**5),
)
def test_any_start_up_and_cost_are_recovered(start: int, cost: int, first: int, more: int) -> None:
    second = first + more
    assert per_transaction(
        (first, start + first * cost), (second, start + second * cost)
    ) == pytest.approx(cost)


@pytest.mark.parametrize("served", [(500, 500), (500, 400)])
def test_a_long_run_that_served_no_more_is_an_error(served: tuple[int, int]) -> None:
    with pytest.raises(ValueError, match="long run served"):
        per_transaction((served[0], 10**9), (served[1], 2 * 10**9))


def test_the_whole_process_count_is_read_from_callgrind_output(tmp_path: Path) -> None:
    out = tmp_path / "callgrind.out"
    out.write_text(
        "version: 1\ncreator: callgrind-3.19.0\ncmd: python\nevents: Ir\n"
        "fl=(1) x.c\nfn=(1) main\n5 1000\nsummary: 1344804621\n\n\ntotals: 1344806033\n"
    )
    assert instructions_in(out) == 1_344_804_621
    out.write_text("events: Ir\n")  # the process was killed before it wrote its counts
    with pytest.raises(ValueError, match="no 'summary:'"):
        instructions_in(out)
