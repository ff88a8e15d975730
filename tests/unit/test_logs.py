"""Logging setup (text and JSON lines) and the rate limiter for repeating faults.

The rate limiter runs on a scheduler the test drives by hand (a clock and a
timer list, the two things it takes from an event loop), so windows of 60 s
pass in no time; one test runs it on a real asyncio loop, waiting on the event
of the summary being logged.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
from collections.abc import Callable, Iterator

import pytest

from gateway.logs import JsonFormatter, RateLimitedLogger, setup_logging
from tests.helpers import LogCollector


class ManualScheduler:
    """A clock that moves only when told, and the timers due by then."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.timers: list[ManualTimer] = []

    def time(self) -> float:
        return self.now

    def call_later(self, delay: float, callback: Callable[[], object], /) -> ManualTimer:
        timer = ManualTimer(self.now + delay, callback)
        self.timers.append(timer)
        return timer

    def advance(self, seconds: float) -> None:
        self.now += seconds
        due = [t for t in self.timers if t.when <= self.now and not t.cancelled]
        self.timers = [t for t in self.timers if t not in due and not t.cancelled]
        for timer in sorted(due, key=lambda t: t.when):
            timer.callback()


class ManualTimer:
    def __init__(self, when: float, callback: Callable[[], object]) -> None:
        self.when = when
        self.callback = callback
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


@pytest.fixture
def logger(request: pytest.FixtureRequest) -> Iterator[tuple[logging.Logger, LogCollector]]:
    log = logging.getLogger(f"test.logs.{request.node.name}")
    log.setLevel(logging.DEBUG)
    log.propagate = False
    handler = LogCollector()
    log.addHandler(handler)
    yield log, handler
    log.removeHandler(handler)


def test_first_occurrence_at_once_then_one_summary_with_the_count(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger
    scheduler = ManualScheduler()
    limiter = RateLimitedLogger(log, scheduler, window=60.0)
    limiter.note("unit 5 on line a", "timeout", "no answer within 1 s")
    assert seen.messages == ["unit 5 on line a: timeout: no answer within 1 s"]
    assert seen.records[0].levelno == logging.WARNING
    for _ in range(37):
        scheduler.advance(1.0)
        limiter.note("unit 5 on line a", "timeout", "no answer within 1 s")
    assert len(seen.messages) == 1
    scheduler.advance(60.0 - 37.0)
    assert seen.messages[1:] == ["unit 5 on line a: 37 more timeouts in the last 60 s"]
    assert seen.records[1].levelno == logging.WARNING


def test_a_quiet_window_ends_silently_and_the_next_fault_is_a_first_again(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger
    scheduler = ManualScheduler()
    limiter = RateLimitedLogger(log, scheduler, window=60.0)
    limiter.note("unit 5 on line a", "CRC error")
    scheduler.advance(61.0)
    assert seen.messages == ["unit 5 on line a: CRC error"]
    limiter.note("unit 5 on line a", "CRC error")
    limiter.note("unit 5 on line a", "CRC error")
    scheduler.advance(60.0)
    assert seen.messages == [
        "unit 5 on line a: CRC error",
        "unit 5 on line a: CRC error",
        "unit 5 on line a: 1 more CRC error in the last 60 s",
    ]


def test_subjects_and_faults_are_limited_separately(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger
    scheduler = ManualScheduler()
    limiter = RateLimitedLogger(log, scheduler, window=10.0)
    for _ in range(3):
        limiter.note("unit 5 on line a", "timeout")
        limiter.note("unit 6 on line a", "timeout")
        limiter.note("unit 5 on line a", "CRC error")
        limiter.note("line a", "discarded input", level=logging.INFO, plural="discarded inputs")
    scheduler.advance(10.0)
    assert seen.messages == [
        "unit 5 on line a: timeout",
        "unit 6 on line a: timeout",
        "unit 5 on line a: CRC error",
        "line a: discarded input",
        "unit 5 on line a: 2 more timeouts in the last 10 s",
        "unit 6 on line a: 2 more timeouts in the last 10 s",
        "unit 5 on line a: 2 more CRC errors in the last 10 s",
        "line a: 2 more discarded inputs in the last 10 s",
    ]
    assert seen.records[3].levelno == seen.records[7].levelno == logging.INFO


def test_flush_writes_pending_summaries_and_cancels_the_timers(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger
    scheduler = ManualScheduler()
    limiter = RateLimitedLogger(log, scheduler, window=60.0)
    for _ in range(5):
        limiter.note("unit 1 on line b", "timeout")
    scheduler.advance(12.0)
    limiter.flush()
    assert seen.messages == [
        "unit 1 on line b: timeout",
        "unit 1 on line b: 4 more timeouts in the last 12 s",
    ]
    assert all(timer.cancelled for timer in scheduler.timers)
    scheduler.advance(60.0)
    assert len(seen.messages) == 2


def test_nothing_is_remembered_while_the_level_is_off(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger
    log.setLevel(logging.ERROR)
    scheduler = ManualScheduler()
    limiter = RateLimitedLogger(log, scheduler)
    for _ in range(3):
        limiter.note("unit 1 on line a", "timeout")
    assert seen.messages == [] and scheduler.timers == []


def test_on_a_real_event_loop_the_summary_comes_when_the_window_ends(
    logger: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = logger

    async def scenario() -> list[str]:
        loop = asyncio.get_running_loop()
        summary_logged = loop.create_future()
        original_emit = seen.emit

        def emit(record: logging.LogRecord) -> None:
            original_emit(record)
            if "more" in record.getMessage() and not summary_logged.done():
                summary_logged.set_result(None)

        seen.emit = emit  # type: ignore[method-assign]
        limiter = RateLimitedLogger(log, loop, window=0.02)
        for _ in range(4):
            limiter.note("unit 9 on line c", "timeout")
        await asyncio.wait_for(summary_logged, 5.0)
        return seen.messages

    assert asyncio.run(scenario()) == [
        "unit 9 on line c: timeout",
        "unit 9 on line c: 3 more timeouts in the last 0 s",
    ]


@pytest.fixture
def root_logging() -> Iterator[None]:
    """Give the root logger back as it was (pytest's own handlers included)."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in list(root.handlers):
        root.removeHandler(handler)
    for handler in handlers:
        root.addHandler(handler)
    root.setLevel(level)


@pytest.mark.usefixtures("root_logging")
def test_json_lines_carry_the_extra_fields_and_the_exception() -> None:
    stream = io.StringIO()
    setup_logging("info", "json", stream)
    log = logging.getLogger("gateway.test")
    log.info("unit %d answers", 5, extra={"line": "a", "latency_ms": 1.5})
    log.debug("not at info")
    try:
        raise OSError("port gone")
    except OSError:
        log.exception("line a lost")
    first, second = (json.loads(line) for line in stream.getvalue().splitlines())
    assert first["message"] == "unit 5 answers"
    assert (first["level"], first["logger"]) == ("info", "gateway.test")
    assert (first["line"], first["latency_ms"]) == ("a", 1.5)
    assert first["time"].endswith("Z") and "T" in first["time"]
    assert "OSError: port gone" in second["exception"]
    assert second["level"] == "error"


@pytest.mark.usefixtures("root_logging")
def test_text_is_the_default_and_the_level_is_applied() -> None:
    stream = io.StringIO()
    setup_logging("warning", stream=stream)
    logging.getLogger("gateway.test").info("hidden")
    logging.getLogger("gateway.test").warning("shown %s", "here")
    [line] = stream.getvalue().splitlines()
    assert line.endswith("WARNING gateway.test: shown here")


def test_json_formatter_never_fails_on_odd_extra_values() -> None:
    record = logging.LogRecord("x", logging.INFO, __file__, 1, "m", None, None)
    record.payload = b"\x01\x02"
    assert json.loads(JsonFormatter().format(record))["payload"] == "b'\\x01\\x02'"
