"""The precise clock on a real event loop: never early, re-armed and disarmed as asked.

Lateness is bounded loosely (a busy 2-core machine); earliness not at all: a frame
sent before t3.5 has passed is a protocol violation, a late one only costs time.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from gateway.io.clock import _FALLBACK_MARGIN, COARSE_LIMIT, SPIN_MARGIN, PreciseClock, wait_until

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


@pytest.mark.parametrize("delay", [0.0005, 0.003, COARSE_LIMIT * 2.5])
def test_ahead_calls_back_within_the_last_stretch_and_wait_until_is_never_early(
    delay: float,
) -> None:
    """``ahead``: the callback may come early, by at most the last stretch; the act that
    follows ``wait_until(deadline)`` never comes early."""

    async def scenario() -> None:
        clock = PreciseClock(asyncio.get_running_loop())
        fired = asyncio.Event()
        called_at: list[float] = []
        acted_at: list[float] = []

        def callback() -> None:
            called_at.append(time.monotonic())
            wait_until(deadline)
            acted_at.append(time.monotonic())
            fired.set()

        deadline = time.monotonic() + delay
        clock.arm(deadline, callback, ahead=True)
        await asyncio.wait_for(fired.wait(), 5.0)
        stretch = 2 * SPIN_MARGIN if clock.uses_timerfd else 2 * _FALLBACK_MARGIN
        clock.close()
        assert called_at[0] >= deadline - stretch - 1e-6
        assert acted_at[0] >= deadline
        assert acted_at[0] - deadline < LATE_BOUND_S
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


@pytest.mark.parametrize("order", ["later", "earlier"])
def test_a_far_deadline_moved_fires_once_at_the_new_time(order: str) -> None:
    """A far deadline moved later keeps its loop timer (woken early, it waits on); moved
    earlier, it gets a new one. Either way the callback runs once, never before its time."""

    async def scenario() -> None:
        clock = PreciseClock(asyncio.get_running_loop())
        fired_at: list[float] = []
        done = asyncio.Event()

        def callback() -> None:
            fired_at.append(time.monotonic())
            done.set()

        now = time.monotonic()
        first, second = now + 3 * COARSE_LIMIT, now + 6 * COARSE_LIMIT
        if order == "earlier":
            first, second = second, first
        clock.arm(first, callback)
        clock.arm(second, callback)
        await asyncio.wait_for(done.wait(), 5.0)
        # Long enough for a stale wake-up at the other deadline to show itself.
        await asyncio.sleep(max(first, second) - time.monotonic() + 4 * COARSE_LIMIT)
        clock.close()
        assert len(fired_at) == 1
        assert second <= fired_at[0] < second + LATE_BOUND_S

    asyncio.run(scenario())


def test_a_disarmed_far_deadline_never_fires_and_its_timer_serves_the_next() -> None:
    async def scenario() -> None:
        clock = PreciseClock(asyncio.get_running_loop())
        calls: list[str] = []
        done = asyncio.Event()
        clock.arm(time.monotonic() + 2 * COARSE_LIMIT, lambda: calls.append("disarmed"))
        clock.disarm()
        later = time.monotonic() + 5 * COARSE_LIMIT

        def second() -> None:
            calls.append("second")
            done.set()

        clock.arm(later, second)
        await asyncio.wait_for(done.wait(), 5.0)
        assert time.monotonic() >= later
        clock.close()
        assert calls == ["second"]

    asyncio.run(scenario())
