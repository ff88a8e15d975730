"""The precise clock on a real event loop: never early, re-armed and disarmed as asked.

Lateness is bounded loosely (a busy 2-core machine); earliness not at all: a frame
sent before t3.5 has passed is a protocol violation, a late one only costs time.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from gateway.io.clock import COARSE_LIMIT, PreciseClock

LATE_BOUND_S = 0.05


@pytest.mark.parametrize("delay", [0.0005, 0.003, COARSE_LIMIT * 2.5])
def test_a_deadline_is_met_never_early(delay: float) -> None:
    async def scenario() -> None:
        clock = PreciseClock(asyncio.get_running_loop())
        fired = asyncio.Event()
        fired_at: list[float] = []

        def callback() -> None:
            fired_at.append(time.monotonic())
            fired.set()

        deadline = time.monotonic() + delay
        clock.arm(deadline, callback)
        await asyncio.wait_for(fired.wait(), 5.0)
        clock.close()
        assert fired_at[0] >= deadline
        assert fired_at[0] - deadline < LATE_BOUND_S
        assert clock.deadline == 0.0

    asyncio.run(scenario())


def test_rearming_replaces_and_disarming_cancels() -> None:
    async def scenario() -> None:
        clock = PreciseClock(asyncio.get_running_loop())
        calls: list[str] = []
        done = asyncio.Event()

        def first() -> None:
            calls.append("first")

        def second() -> None:
            calls.append("second")
            done.set()

        now = time.monotonic()
        clock.arm(now + 0.002, first)
        clock.arm(now + COARSE_LIMIT * 2, second)  # far: the loop's timer, then the precise one
        await asyncio.wait_for(done.wait(), 5.0)
        assert calls == ["second"]
        clock.arm(time.monotonic() + 0.002, first)
        clock.disarm()
        # Nothing fires: a later deadline armed after the disarm is the only one that runs.
        done.clear()
        clock.arm(time.monotonic() + 0.01, second)
        await asyncio.wait_for(done.wait(), 5.0)
        assert calls == ["second", "second"]
        clock.close()

    asyncio.run(scenario())
