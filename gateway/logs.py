"""Logging set up in one place: readable text by default, JSON lines for Docker and journald.

Also the ``RateLimitedLogger``: a slave that stopped answering times out on
every poll, and one log line per request would bury everything else. The
first occurrence of a fault is logged at once; repeats within the window are
only counted, and one summary line with the count ends the window.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
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

    def __init__(self, logger: logging.Logger, scheduler: Scheduler, window: float = 60.0) -> None:
        self._logger = logger
        self._scheduler = scheduler
        self.window = window
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
        """Record one occurrence of ``fault`` (a singular noun) for ``subject``."""
        key = (subject, fault)
        current = self._windows.get(key)
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
