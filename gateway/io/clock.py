"""Sub-millisecond deadlines on an asyncio loop.

The loop's timers are millisecond-grained (uvloop rounds ``call_at`` to 1 ms,
and epoll timeouts are in ms), which is too coarse for a 1.75 ms t3.5. A Linux
timerfd watched with ``add_reader`` wakes the loop with the kernel's own
precision (measured here: ~60-90 us late at the median, ~200 us at p99 on a
busy 2-core VM), so we arm it ``SPIN_MARGIN`` early and spend the last stretch
polling ``time.monotonic()``: a wait ends within a few microseconds of its
deadline and spins for at most ``SPIN_MARGIN`` per wait. Where timerfd is
missing we fall back to ``call_at`` about 1.5 ms early, then the same spin.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable

from . import timerfd

SPIN_MARGIN = 0.00025
#: Deadlines further away than this wait on the loop's timer before the precise one.
COARSE_LIMIT = 0.02
_FALLBACK_MARGIN = 0.0015


class PreciseClock:
    """One re-armable deadline on ``time.monotonic()``, met to a few microseconds.

    A line driver arms it with the core's next deadline (``arm``); the callback runs
    at that time, never before it. Re-arming replaces the deadline; ``disarm``
    cancels it. One clock serves one line.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._fd = timerfd.create()
        if self._fd >= 0:
            loop.add_reader(self._fd, self._on_timerfd)
        self._deadline = 0.0  # 0: not armed
        self._callback: Callable[[], None] | None = None
        self._fallback: asyncio.TimerHandle | None = None
        self._fallback_at = 0.0  # when ``_fallback`` wakes the clock (monotonic seconds)
        self._fd_armed = False
        self._ahead = False

    @property
    def uses_timerfd(self) -> bool:
        """True when waits use a kernel timerfd (Linux)."""
        return self._fd >= 0

    @property
    def deadline(self) -> float:
        """The armed deadline, 0 when disarmed."""
        return self._deadline

    def close(self) -> None:
        """Disarm and release the timerfd."""
        self.disarm()
        if self._fallback is not None:
            self._fallback.cancel()
            self._fallback = None
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1

    def arm(self, deadline: float, callback: Callable[[], None], *, ahead: bool = False) -> None:
        """Call ``callback`` at ``deadline`` (``time.monotonic()`` seconds), replacing any other.

        With ``ahead``, the callback runs at the start of the last stretch instead (up to
        ``2 * SPIN_MARGIN`` early, or ``2 * _FALLBACK_MARGIN`` without a timerfd), and
        it is the caller's to decide what happens at ``deadline`` and ``wait_until`` it
        before acting: the stretch is spent deciding rather than spinning, so the act comes
        on time even when the deciding is slow (its code and data cold after a quiet spell).

        A deadline more than ``COARSE_LIMIT`` away (a response timeout) first waits on the
        loop's own timer, which costs no system call, and is re-armed precisely when near:
        most are replaced long before they come (the answer arrives). A loop timer that
        wakes no later than a new far deadline needs is kept (it re-arms for the deadline
        then), so a line that arms one response timeout per transaction creates about one
        loop timer per timeout period, not one per transaction.
        """
        self._callback = callback
        self._ahead = ahead
        if deadline == self._deadline:
            return
        self._deadline = deadline
        now = time.monotonic()
        if self._fd < 0 or deadline - now > COARSE_LIMIT:
            if self._fd_armed:  # ``_disarm_timerfd``, its test inline: once per transaction
                self._disarm_timerfd()
            wake_at = deadline - _FALLBACK_MARGIN
            if self._fallback is not None:
                if self._fallback_at <= wake_at:
                    return  # it wakes in time, and ``_fire`` waits on from there
                self._fallback.cancel()
            self._fallback_at = wake_at
            self._fallback = self._loop.call_later(max(0.0, wake_at - now), self._on_fallback)
            return
        if self._fallback is not None:
            self._fallback.cancel()
            self._fallback = None
        self._arm_timerfd(deadline)

    def disarm(self) -> None:
        """Cancel the armed deadline.

        A pending loop timer is left to wake once with nothing to do, or to serve the
        next far deadline (see ``arm``); a cancelled callback never runs.
        """
        self._deadline = 0.0
        self._callback = None
        if self._fd_armed:  # ``_disarm_timerfd``, its test inline: once per transaction
            self._disarm_timerfd()

    def _arm_timerfd(self, deadline: float) -> None:
        timerfd.arm_at(self._fd, max(deadline - SPIN_MARGIN, 1e-6))  # 0 would disarm it
        self._fd_armed = True

    def _disarm_timerfd(self) -> None:
        if self._fd_armed:
            timerfd.disarm(self._fd)
            self._fd_armed = False

    def _on_timerfd(self) -> None:
        try:
            os.read(self._fd, 8)
        except BlockingIOError:
            return
        self._fd_armed = False
        self._fire()

    def _on_fallback(self) -> None:
        self._fallback = None
        self._fire()

    def _fire(self) -> None:
        deadline = self._deadline
        callback = self._callback
        if not deadline or callback is None:
            return
        remaining = deadline - time.monotonic()
        if remaining > COARSE_LIMIT or (self._fd < 0 and remaining > 2 * _FALLBACK_MARGIN):
            if self._fallback is None:
                self._fallback_at = deadline - _FALLBACK_MARGIN
                self._fallback = self._loop.call_later(
                    remaining - _FALLBACK_MARGIN, self._on_fallback
                )
            return  # woken early (or re-armed since): wait again
        if self._fd >= 0 and remaining > 2 * SPIN_MARGIN and not self._fd_armed:
            self._arm_timerfd(deadline)  # near now: the precise timer takes over
            return
        if remaining > 2 * _FALLBACK_MARGIN:
            return  # a wake-up for an earlier deadline; the timerfd waits for this one
        if not self._ahead:
            wait_until(deadline)  # the last stretch
        self._deadline = 0.0
        self._callback = None
        callback()


def wait_until(deadline: float) -> None:
    """Spin until ``time.monotonic()`` reaches ``deadline`` (a stretch of microseconds)."""
    while time.monotonic() < deadline:
        pass
