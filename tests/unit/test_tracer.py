"""The frame trace's lines, filters and bounded memory, with a clock the test moves by hand."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator

import pytest

from gateway.cli import build_parser
from gateway.core.outcome import Outcome
from gateway.io.frame_trace import FrameTrace, parse_function, reply_outcome
from gateway.io.http.live import TraceFilter, TraceHub, TraceStream
from gateway.io.status import LineStatus, MasterStatus, PairStatus
from gateway.logs import JsonFormatter
from gateway.metrics import GatewayMetrics
from gateway.trace import MAX_PENDING, Tracer
from tests.helpers import LogCollector

READ_10 = bytes.fromhex("03 0000 000A")
READ_10_ANSWER = bytes.fromhex("03 14") + bytes(20)


class Clock:
    def __init__(self) -> None:
        self.now = 50.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def traced(request: pytest.FixtureRequest) -> Iterator[tuple[logging.Logger, LogCollector]]:
    log = logging.getLogger(f"test.trace.{request.node.name}")
    log.propagate = False
    handler = LogCollector()
    log.addHandler(handler)
    yield log, handler
    log.removeHandler(handler)


def test_request_and_reply_lines_with_latency(traced: tuple[logging.Logger, LogCollector]) -> None:
    log, seen = traced
    clock = Clock()
    tracer = Tracer(logger=log, clock=clock)
    tracer.request("10.0.0.7:50432", 17, 5, READ_10)
    clock.now += 0.02261
    tracer.reply("10.0.0.7:50432", 17, 5, READ_10_ANSWER, Outcome.OK)
    assert seen.messages == [
        "-> 10.0.0.7:50432 tid=17 unit=5 read_holding_registers(3) address=0 quantity=10",
        "<- 10.0.0.7:50432 tid=17 unit=5 read_holding_registers(3) byte_count=20 ok 22.61 ms",
    ]
    assert all(record.levelno == logging.INFO for record in seen.records)


def test_tracing_is_on_whatever_the_log_level(traced: tuple[logging.Logger, LogCollector]) -> None:
    log, seen = traced
    log.setLevel(logging.ERROR)
    Tracer(logger=log).request("m", 1, 1, READ_10)
    assert len(seen.records) == 1


def test_outcome_from_the_reply_when_the_caller_does_not_say(
    traced: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = traced
    tracer = Tracer(logger=log)
    tracer.reply("m", 1, 1, bytes((0x83, 0x0A)))
    tracer.reply("m", 2, 1, bytes((0x83, 0x0B)))
    tracer.reply("m", 3, 1, bytes((0x83, 0x02)))
    tracer.reply("m", 4, 1, bytes((0x83, 0x03)), Outcome.REJECTED)
    tracer.reply("m", 5, 1, bytes.fromhex("06 0001 0007"))
    assert [message.split(" ", 5)[-1] for message in seen.messages] == [
        "exception=0x0A no_route",
        "exception=0x0B target_failed",
        "exception=0x02 slave_exception",
        "exception=0x03 rejected",
        "address=1 value=0x0007 ok",
    ]


def test_filters_by_unit_and_function(traced: tuple[logging.Logger, LogCollector]) -> None:
    log, seen = traced
    tracer = Tracer(units=[5], functions=[3, 16], logger=log)
    tracer.request("m", 1, 5, READ_10)
    tracer.request("m", 2, 6, READ_10)  # other unit
    tracer.request("m", 3, 5, bytes.fromhex("06 0001 0007"))  # other function
    tracer.reply("m", 1, 5, bytes((0x83, 0x0B)))  # an exception to a traced function
    tracer.reply("m", 2, 6, READ_10_ANSWER)
    tracer.dropped("m", 3, 5, 6)
    tracer.dropped("m", 4, 5, 16)
    assert [message.split()[:3] for message in seen.messages] == [
        ["->", "m", "tid=1"],
        ["<-", "m", "tid=1"],
        ["x", "m", "tid=4"],
    ]
    assert seen.messages[2].endswith("write_multiple_registers(16) dropped: the master left")


def test_requests_without_reply_are_forgotten_past_the_bound(
    traced: tuple[logging.Logger, LogCollector],
) -> None:
    log, seen = traced
    log.disabled = True  # the formatting is not what this test is about
    tracer = Tracer(logger=log)
    for tid in range(MAX_PENDING + 100):
        tracer.request("gone", tid, 1, READ_10)
    log.disabled = False
    tracer.reply("gone", 0, 1, READ_10_ANSWER)  # the oldest: forgotten, so no latency
    tracer.reply("gone", MAX_PENDING + 99, 1, READ_10_ANSWER)
    first, last = seen.records
    assert first.__dict__["latency_ms"] is None and first.getMessage().endswith(" ok")
    assert last.__dict__["latency_ms"] is not None


def test_json_lines_give_every_field(traced: tuple[logging.Logger, LogCollector]) -> None:
    log, seen = traced
    clock = Clock()
    tracer = Tracer(logger=log, clock=clock)
    tracer.request("10.0.0.7:50432", 9, 1, READ_10)
    clock.now += 0.5
    tracer.reply("10.0.0.7:50432", 9, 1, READ_10_ANSWER, Outcome.OK)
    entry = json.loads(JsonFormatter().format(seen.records[1]))
    assert {key: entry[key] for key in entry if key not in ("time", "message")} == {
        "level": "info",
        "logger": log.name,
        "direction": "reply",
        "peer": "10.0.0.7:50432",
        "transaction_id": 9,
        "unit": 1,
        "function": "read_holding_registers",
        "function_code": 3,
        "detail": "byte_count=20",
        "outcome": "ok",
        "latency_ms": 500.0,
    }


@pytest.mark.parametrize(
    ("text", "code"),
    [("3", 3), ("0x10", 16), ("read_holding_registers", 3), (" Read_Coils ", 1), ("127", 127)],
)
def test_function_codes_by_number_or_name(text: str, code: int) -> None:
    assert parse_function(text) == code


@pytest.mark.parametrize("text", ["0", "128", "readholding", ""])
def test_function_codes_that_are_not(text: str) -> None:
    with pytest.raises(ValueError):
        parse_function(text)


def test_trace_flags_on_the_command_line() -> None:
    args = build_parser().parse_args(
        ["--trace-unit", "5", "--trace-unit", "6", "--trace-function", "read_coils",
         "--trace-function", "0x10"]
    )  # fmt: skip
    assert (args.trace, args.trace_unit, args.trace_function) == (False, [5, 6], [1, 16])
    assert build_parser().parse_args(["--trace"]).trace
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--trace-function", "nope"])


class Recorder:
    """A subscriber that keeps what it hears."""

    def __init__(self) -> None:
        self.heard: list[tuple[str, int, Outcome | None]] = []

    def request(
        self,
        peer: str,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        listener: str | None = None,
        role: str | None = None,
    ) -> None:
        self.heard.append(("request", transaction_id, None))

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        self.heard.append(("reply", transaction_id, outcome))

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        self.heard.append(("dropped", transaction_id, Outcome.DROPPED))


def test_the_frame_trace_reaches_its_subscribers_of_the_moment() -> None:
    first, second = Recorder(), Recorder()
    trace = FrameTrace(first)
    trace.request("m", 1, 1, READ_10)
    trace.subscribe(second)
    trace.subscribe(second)  # once, however often
    trace.reply("m", 1, 1, READ_10_ANSWER, Outcome.OK)
    trace.unsubscribe(first)
    trace.dropped("m", 2, 1, 3)
    trace.unsubscribe(first)  # not subscribed: nothing happens
    assert first.heard == [("request", 1, None), ("reply", 1, Outcome.OK)]
    assert second.heard == [("reply", 1, Outcome.OK), ("dropped", 2, Outcome.DROPPED)]
    assert trace.subscribers == (second,) and trace.active
    trace.unsubscribe(second)
    assert not trace.active and not FrameTrace().active  # listeners call it only when active


@pytest.mark.parametrize(
    ("pdu", "outcome"),
    [
        (b"", Outcome.BROADCAST),
        (READ_10_ANSWER, Outcome.OK),
        (bytes((0x83, 0x0A)), Outcome.NO_ROUTE),
        (bytes((0x83, 0x0B)), Outcome.TARGET_FAILED),
        (bytes((0x83, 0x02)), Outcome.SLAVE_EXCEPTION),
        (bytes((0x83,)), Outcome.SLAVE_EXCEPTION),
    ],
)
def test_a_reply_says_its_outcome_when_the_listener_does_not(pdu: bytes, outcome: Outcome) -> None:
    assert reply_outcome(pdu) is outcome


class NoGateway:
    """A ``GatewayView`` with no line and no master."""

    def route(self, unit: int) -> tuple[str, int] | None:
        return ("a", unit) if unit == 1 else None

    def line_states(self) -> list[LineStatus]:
        return []

    def masters(self) -> tuple[MasterStatus, ...]:
        return ()

    def listen(self) -> str:
        return ""

    def pair_status(self) -> PairStatus | None:
        return None


def test_the_live_hub_subscribes_while_a_stream_is_open() -> None:
    trace, logger = FrameTrace(), Recorder()
    trace.subscribe(logger)
    hub = TraceHub(trace, NoGateway(), GatewayMetrics(), clock=Clock())
    assert not hub.attached and trace.subscribers == (logger,)
    stream = TraceStream(TraceFilter())
    hub.add(stream)
    assert hub.attached and trace.subscribers == (logger, hub)
    trace.request("m", 7, 1, READ_10)
    trace.reply("m", 7, 1, bytes((0x83, 0x0B)))
    assert [(e.direction, e.line, e.slave, e.outcome) for e in stream.events] == [
        ("request", "a", 1, None),
        ("reply", "a", 1, Outcome.TARGET_FAILED),
    ]
    hub.remove(stream)
    assert not hub.attached and trace.subscribers == (logger,)
    assert [kind for kind, _tid, _outcome in logger.heard] == ["request", "reply"]
