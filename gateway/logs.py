"""Logging set up in one place: readable text by default, JSON lines for Docker and journald.

Also the ``RateLimitedLogger``: a slave that stopped answering times out on
every poll, and one log line per request would bury everything else. The
first occurrence of a fault is logged at once; repeats within the window are
only counted, and one summary line with the count ends the window. The number
of open windows is bounded too: a client that changes its address cannot make
the limiter itself grow.

And the ``EventSummary``: events that a remote client can cause at will
(connects, disconnects, refusals) are logged one by one only at DEBUG, and
counted into one INFO line per interval, so no client can flood the log.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, TextIO

#: Attributes every ``LogRecord`` has; anything else came in through ``extra=`` and is
#: written as a field of its own in JSON lines (the trace uses this).
_RECORD_ATTRIBUTES = frozenset(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {
    "message",
    "asctime",
    "taskName",
}

TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, the ``extra`` fields, exception."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in record.__dict__.items():
            if key not in _RECORD_ATTRIBUTES and key not in entry:
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False, default=str)


def setup_logging(level: str = "info", fmt: str = "text", stream: TextIO | None = None) -> None:
    """Configure the root logger; calling again replaces the previous setup (tests, reload)."""
    handler = logging.StreamHandler(stream or sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())


class Timer(Protocol):
    """A pending call that can be called off (``asyncio.TimerHandle``)."""

    def cancel(self) -> None: ...


class Scheduler(Protocol):
    """What the rate limiter needs from an event loop (``asyncio`` loops fit): clock, timer."""

    def time(self) -> float: ...

    def call_later(self, delay: float, callback: Callable[[], object], /) -> Timer: ...


@dataclass(slots=True)
class _Window:
    started: float
    level: int
    plural: str
    suppressed: int = 0
    timer: Timer | None = None


class RateLimitedLogger:
    """Logs the first occurrence of each (subject, fault) at once, then one summary per window.

    ``note("unit 5 on line a", "timeout", "no answer within 1.0 s")`` logs
    ``unit 5 on line a: timeout: no answer within 1.0 s``; 37 more notes in the
    next ``window`` seconds are counted, and when the window ends (a loop timer,
    so the summary comes even if the fault stops) one line says
    ``unit 5 on line a: 37 more timeouts in the last 60 s``. A window that saw
    no repeat closes silently, and the next occurrence is a "first" again.
    """

    #: Subject used for faults noted while ``max_windows`` windows are already open.
    OVERFLOW_SUBJECT = "other sources"

    def __init__(
        self,
        logger: logging.Logger,
        scheduler: Scheduler,
        window: float = 60.0,
        max_windows: int = 256,
    ) -> None:
        self._logger = logger
        self._scheduler = scheduler
        self.window = window
        self.max_windows = max_windows
        self._windows: dict[tuple[str, str], _Window] = {}

    def note(
        self,
        subject: str,
        fault: str,
        detail: str = "",
        *,
        level: int = logging.WARNING,
        plural: str | None = None,
    ) -> None:
        """Record one occurrence of ``fault`` (a singular noun) for ``subject``.

        While ``max_windows`` windows are open, a new subject is folded into
        ``OVERFLOW_SUBJECT`` (one window per fault), so memory and lines stay bounded.
        """
        key = (subject, fault)
        current = self._windows.get(key)
        if current is None and len(self._windows) >= self.max_windows:
            key = (self.OVERFLOW_SUBJECT, fault)
            current = self._windows.get(key)
            subject = self.OVERFLOW_SUBJECT
        if current is not None:
            current.suppressed += 1
            return
        if not self._logger.isEnabledFor(level):
            return
        if detail:
            self._logger.log(level, "%s: %s: %s", subject, fault, detail)
        else:
            self._logger.log(level, "%s: %s", subject, fault)
        current = _Window(self._scheduler.time(), level, plural or fault + "s")
        self._windows[key] = current
        current.timer = self._scheduler.call_later(self.window, lambda: self._close(key))

    def _close(self, key: tuple[str, str]) -> None:
        window = self._windows.pop(key, None)
        if window is not None:
            self._summarise(key, window)

    def _summarise(self, key: tuple[str, str], window: _Window) -> None:
        if not window.suppressed:
            return
        subject, fault = key
        noun = fault if window.suppressed == 1 else window.plural
        elapsed = self._scheduler.time() - window.started
        self._logger.log(
            window.level,
            "%s: %d more %s in the last %.0f s",
            subject,
            window.suppressed,
            noun,
            elapsed,
        )

    def flush(self) -> None:
        """Write the pending summaries now (at shutdown) and forget every window."""
        windows, self._windows = self._windows, {}
        for key, window in windows.items():
            if window.timer is not None:
                window.timer.cancel()
            self._summarise(key, window)


@dataclass(slots=True)
class _Interval:
    counts: Counter[str] = field(default_factory=Counter)
    sources: Counter[str] = field(default_factory=Counter)
    other_sources: int = 0


class EventSummary:
    """Counts events per interval and logs one INFO summary line when an interval ends.

    ``note("opened", "10.0.0.7")`` counts one event of a kind for a source; the
    first note of an interval arms a timer, and when it fires one line says
    ``connections in the last 60 s: 12 opened, 11 closed, 3 refused; most from
    10.0.0.7 (20 events)``. Intervals without events log nothing. At most
    ``max_sources`` distinct sources are counted by name per interval; the
    rest are counted together.
    """

    def __init__(
        self,
        logger: logging.Logger,
        scheduler: Scheduler,
        what: str,
        interval: float = 60.0,
        max_sources: int = 1024,
        extra: Callable[[], str] | None = None,
    ) -> None:
        self._logger = logger
        self._scheduler = scheduler
        self._what = what
        self.interval = interval
        self.max_sources = max_sources
        self._extra = extra
        self._current: _Interval | None = None
        self._started = 0.0
        self._timer: Timer | None = None

    def note(self, kind: str, source: str) -> None:
        """Count one event of ``kind`` (a past participle: opened, refused) from ``source``."""
        current = self._current
        if current is None:
            current = self._current = _Interval()
            self._started = self._scheduler.time()
            self._timer = self._scheduler.call_later(self.interval, self.flush)
        current.counts[kind] += 1
        sources = current.sources
        if source in sources or len(sources) < self.max_sources:
            sources[source] += 1
        else:
            current.other_sources += 1

    def flush(self) -> None:
        """Log the interval's summary now (the timer calls this; so does a stop)."""
        current, self._current = self._current, None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if current is None or not current.counts:
            return
        elapsed = self._scheduler.time() - self._started
        counts = ", ".join(f"{count} {kind}" for kind, count in current.counts.most_common())
        source, events = current.sources.most_common(1)[0]
        extra = f"; {self._extra()}" if self._extra is not None else ""
        self._logger.info(
            "%s in the last %.0f s: %s; most from %s (%d events)%s",
            self._what,
            elapsed,
            counts,
            source,
            events,
            extra,
        )
