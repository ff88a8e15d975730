"""Linux's timerfd and timer slack through ctypes (Python 3.11 has no ``os.timerfd_*``).

Kept apart from ``clock`` so that the clock compiles in the compiled build: mypyc does
not compile ``ctypes`` structures. Every function is a no-op or says "none" where Linux
or the symbol is missing, and the clock then falls back to the loop's timer.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_CLOCK_MONOTONIC = 1
_TFD_NONBLOCK = 0o4000
_TFD_CLOEXEC = 0o2000000
_TFD_TIMER_ABSTIME = 1
_PR_SET_TIMERSLACK = 29


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _load_libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.timerfd_create  # noqa: B018 - probe that the symbol exists
    except (OSError, AttributeError):
        return None
    return libc


_LIBC = _load_libc()


def create() -> int:
    """A non-blocking, close-on-exec timerfd on ``CLOCK_MONOTONIC``; -1 when there is none.

    Asks for a 1 us timer slack for the calling thread too, instead of the default 50 us.
    """
    if _LIBC is None:
        return -1
    _LIBC.prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)
    fd = int(_LIBC.timerfd_create(_CLOCK_MONOTONIC, _TFD_NONBLOCK | _TFD_CLOEXEC))
    return fd if fd >= 0 else -1


def arm_at(fd: int, when: float) -> None:
    """Make ``fd`` readable at ``when`` (``time.monotonic()`` seconds, > 0)."""
    assert _LIBC is not None
    seconds = int(when)
    spec = _Itimerspec(_Timespec(0, 0), _Timespec(seconds, int((when - seconds) * 1e9)))
    _LIBC.timerfd_settime(fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None)


def disarm(fd: int) -> None:
    """Stop ``fd`` from becoming readable."""
    assert _LIBC is not None
    spec = _Itimerspec(_Timespec(0, 0), _Timespec(0, 0))
    _LIBC.timerfd_settime(fd, 0, ctypes.byref(spec), None)
