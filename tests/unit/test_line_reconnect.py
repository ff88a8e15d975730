"""A network line's connection that stops answering is made again: the core decides.

Literal times on an RTU-over-TCP line (a serial device server): the core emits
``LineEvent.RECONNECT`` with its reason after ``reconnect_after`` answers missed in a row
with nothing heard on the connection, re-sends the reads that were on the wire once the
connection is back, and does not count the silent connection's timeouts against its slaves.
"""

from __future__ import annotations

from gateway.config import build_config
from gateway.core.line import LineCore
from gateway.core.outcome import LineEvent, Outcome, ReconnectReason, SlaveState
from gateway.core.rtu import encode_rtu
from tests.helpers import read
from tests.line_harness import LineHarness


def answer(slave: int) -> bytes:
    return encode_rtu(slave, bytes((3, 2, 0x12, 0x34)))


def device_server(**settings: object) -> LineHarness:
    table = {
        "kind": "rtu-over-tcp",
        "address": "127.0.0.1:4001",
        "units": [1, 2],
        "retries": 0,
        **settings,
    }
    config = build_config({"lines": {"a": table}}).lines[0]
    return LineHarness(LineCore(config, -1.0))


def poll(line: LineHarness, slave: int, now: float, answered: bool) -> float:
    """One read of ``slave`` at ``now``: every frame sent for it (the read, a proof read)
    answered 5 ms later, or none; the core's timers fired until the read is answered.
    Returns when it was."""
    request = line.submit(slave, read(0), now)
    while request in line.unanswered():
        sent = line.frames()
        if sent and answered:
            now += 0.005
            line.receive(answer(slave), now)
            continue
        now = line.timer()
    return now


def reconnects(line: LineHarness) -> list[str]:
    return [note.detail for note in line.notes(LineEvent.RECONNECT)]


def test_a_connection_silent_for_three_answers_is_made_again_and_its_slave_stays_up() -> None:
    line = device_server()
    now = 0.0
    for _ in range(12):
        now = poll(line, 1, now, answered=True) + 0.1
    polls = 0
    while not reconnects(line) and polls < 8:  # three attempts on the wire, a proof read's too
        now = poll(line, 1, now, answered=False) + 0.1
        polls += 1
    assert reconnects(line) == [ReconnectReason.SILENT]
    timeouts = line.notes(LineEvent.TIMEOUT)
    assert len(timeouts) == 3
    assert line.core.reconnecting
    assert line.core.slave_state(1) is SlaveState.UP  # the silence was the connection's
    queued = line.submit(1, read(7), now)  # waits for the new connection, not refused
    assert line.frames() == []
    line.core.port_opened(now + 0.2)
    # The lost answers may still come through the device server: a proof read goes first.
    proof = line.frames()
    assert len(proof) == 1 and proof[0][:4] == encode_rtu(1, read(0))[:4]
    line.receive(encode_rtu(1, bytes((3, proof[0][5] * 2)) + bytes(proof[0][5] * 2)), now + 0.25)
    assert line.frames() == [encode_rtu(1, read(7))]
    line.receive(answer(1), now + 0.3)
    assert line.answer_of(queued)[1] is Outcome.OK


def test_bytes_heard_on_the_connection_start_the_count_again() -> None:
    line = device_server(reconnect_after=2)
    now = 0.0
    for _ in range(12):
        now = poll(line, 1, now, answered=True) + 0.1
    for _ in range(6):  # one silent attempt, then something heard: never two in a row
        now = poll(line, 1, now, answered=False)
        line.receive(bytes.fromhex("00"), now + 0.01)  # noise: the connection is alive
        now += 0.1
    assert len(line.notes(LineEvent.TIMEOUT)) >= 2
    assert reconnects(line) == []


def test_a_read_on_the_wire_goes_again_on_the_new_connection() -> None:
    line = device_server(reconnect_after=1, retries=1)
    now = poll(line, 1, 0.0, answered=True)
    waiting = line.submit(1, read(9), now + 0.1)
    assert line.frames() == [encode_rtu(1, read(9))]
    line.timer()  # no answer, nothing heard: the connection is made again
    assert reconnects(line) == [ReconnectReason.SILENT]
    assert waiting in line.unanswered()  # a read: sent again on the new connection
    line.core.port_opened(line.core.get_timer() or 2.0)
    assert line.frames() == [encode_rtu(1, read(9))]
    line.receive(answer(1), 2.5)
    assert line.answer_of(waiting)[1] is Outcome.OK


def test_a_write_on_the_wire_is_answered_0x0b_at_the_reconnect() -> None:
    line = device_server(reconnect_after=1)
    now = poll(line, 1, 0.0, answered=True)
    write = line.submit(1, bytes.fromhex("0600010005"), now + 0.1)
    line.frames()
    line.core.handle_timer(now + 0.1)  # nothing yet
    line.core.receive(b"", now + 0.2)
    line.core.notes.clear()
    line.core._reconnect(ReconnectReason.OUT_OF_STEP)  # as a bad MBAP header would
    line.flush()
    assert line.answer_of(write)[1] is Outcome.TARGET_FAILED


def test_one_dead_slave_among_live_ones_makes_no_reconnect() -> None:
    """A dead RTU slave behind a device server: the others still answer on the connection,
    so its timeouts are its own, and the connection is kept."""
    line = device_server()
    now = 0.0
    for _ in range(12):
        now = poll(line, 2, now, answered=True) + 0.1
    for _ in range(20):
        if line.core.slave_state(1) is SlaveState.UP:
            now = poll(line, 1, now, answered=False) + 0.1
        now = poll(line, 2, now, answered=True) + 0.1
    assert reconnects(line) == []
    assert line.core.slave_state(1) is not SlaveState.UP


def test_reconnecting_can_be_turned_off() -> None:
    line = device_server(reconnect_after=0)
    now = 0.0
    for _ in range(12):
        now = poll(line, 1, now, answered=True) + 0.1
    for _ in range(6):
        if line.core.slave_state(1) is SlaveState.UP:
            now = poll(line, 1, now, answered=False) + 0.1
    assert reconnects(line) == []
