"""What a line's notes mean for metrics and logs: the event side of a ``Bus``.

The line core notes events (timeouts, CRC errors, discarded input, slave states, a
noisy line, a foreign master's frames); this collaborator counts them and logs each
fault once, then counts repeats (``RateLimitedLogger``). It decides nothing about the line.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping
from typing import Protocol

from ...config import LineConfig
from ...core.line import Note
from ...core.line.foreign import SHARED_FOR_S
from ...core.outcome import LineEvent, ReconnectReason, SlaveState
from ...logs import RateLimitedLogger
from ...metrics import UNIT_LABELS, GatewayMetrics

log = logging.getLogger("gateway.bus")
#: The notes of a line that another master shares (``LineNotes._shared_line``).
_SHARED_LINE_EVENTS = frozenset(
    {LineEvent.FOREIGN_MASTER, LineEvent.SHARED_ANSWER, LineEvent.LINE_NOT_SHARED}
)


class NotedLine(Protocol):
    """What the event side needs of its driver (``bus.Bus``), defined here so that this
    module does not import the driver."""

    @property
    def name(self) -> str: ...
    @property
    def config(self) -> LineConfig: ...
    def slave_states(self) -> Mapping[int, SlaveState]: ...
    def reconnect(self, why: str) -> None: ...


class LineNotes:
    """One bus's notes, counted and logged."""

    def __init__(
        self, bus: NotedLine, metrics: GatewayMetrics, loop: asyncio.AbstractEventLoop
    ) -> None:
        self._bus = bus
        name = self._name = bus.name
        self._metrics = metrics
        self._loop = loop
        self._m_coalesced = metrics.coalesced.labels(name)
        self._m_noisy = metrics.line_noisy.labels(name)
        self._m_noisy.set(0)
        self._m_foreign = metrics.foreign_master_frames.labels(name)
        self.fault_log = RateLimitedLogger(log, loop)  # first fault at once, then counts

    def flush(self) -> None:
        """Log the repeats counted so far (the line closes)."""
        self.fault_log.flush()

    def note(self, note: Note) -> None:
        """Count ``note`` and log it when it is news."""
        event = note.event
        if event is LineEvent.COALESCED:  # the only note on the hot path
            self._m_coalesced.inc()
            return
        metrics = self._metrics
        unit = UNIT_LABELS[note.slave]
        subject = f"unit {unit} on line {self._name}"
        if event is LineEvent.TIMEOUT:
            metrics.timeouts.labels(self._name, unit).inc()
            self.fault_log.note(subject, "timeout", note.detail)
        elif event is LineEvent.CRC_ERROR:
            metrics.crc_errors.labels(self._name, unit).inc()
            self.fault_log.note(subject, "CRC error", note.detail)
        elif event is LineEvent.GARBLED:
            self.fault_log.note(subject, "garbled answer", note.detail)
        elif event is LineEvent.RETRY:
            metrics.retries.labels(self._name, unit).inc()
        elif event is LineEvent.DISCARDED:
            metrics.discarded_frames.labels(self._name, note.detail).inc()
            self.fault_log.note(
                f"line {self._name}",
                "discarded input",
                f"{note.amount} {note.detail} byte(s) or frame(s)",
                level=logging.INFO,
            )
        elif event is LineEvent.LATE_WINDOW:
            metrics.late_windows.labels(self._name).inc()
        elif event is LineEvent.RECONNECT:
            reason = ReconnectReason(note.detail)
            metrics.line_reconnects.labels(self._name, reason).inc()
            why = (
                f"{note.amount} answers missed in a row, nothing heard on it from any slave"
                if reason is ReconnectReason.SILENT
                else "a frame header no Modbus TCP slave sends"
            )
            self._loop.call_soon(self._bus.reconnect, why)
        elif event is LineEvent.PROOF_READ:
            metrics.proof_reads.labels(self._name, unit).inc()
        elif event is LineEvent.SLAVE_STATE:
            self._slave_state(note)
        elif event is LineEvent.LINE_NOISY:
            self._m_noisy.set(1)
            metrics.line_noisy_total.labels(self._name).inc()
            self.fault_log.note(
                f"line {self._name}",
                "noisy line",
                f"{note.detail}; waiting requests answered 0x0B until a gap appears",
            )
        elif event is LineEvent.LINE_QUIET:
            self._m_noisy.set(0)
            log.info("line %s: quiet again, serving requests", self._name)
        elif event in _SHARED_LINE_EVENTS:
            self._shared_line(note, unit, subject)

    def _shared_line(self, note: Note, unit: str, subject: str) -> None:
        """Another master on the line: its frames, the answers held back, and its silence."""
        event = note.event
        if event is LineEvent.FOREIGN_MASTER:
            self._m_foreign.inc()
            self.fault_log.note(
                f"line {self._name}",
                "foreign master frame",
                f"a request to unit {unit} ({note.detail}) this gateway did not send: the line "
                "is shared; answers that may be the other master's are not delivered",
            )
        elif event is LineEvent.SHARED_ANSWER:
            self.fault_log.note(
                subject,
                "answer not delivered",
                note.detail,
                level=logging.INFO,
                plural="answers not delivered",
            )
        else:
            log.info("line %s: no other master heard for %g s", self._name, SHARED_FOR_S)

    def _slave_state(self, note: Note) -> None:
        unit = UNIT_LABELS[note.slave]
        state = note.state
        metrics = self._metrics
        states = list(self._bus.slave_states().values())
        for counted in (SlaveState.SUSPECT, SlaveState.DOWN):
            metrics.slaves_isolated.labels(self._name, counted.value).set(states.count(counted))
        # Per-slave series only for slaves that have answered: a scan of every routed
        # address (all 247 with --serial) must not add two series per absent unit.
        if metrics.heard(self._name, unit):
            metrics.slave_up.labels(self._name, unit).set(0 if state is SlaveState.DOWN else 1)
            metrics.slave_suspect.labels(self._name, unit).set(
                1 if state is SlaveState.SUSPECT else 0
            )
        if state is SlaveState.DOWN:
            log.warning(
                "line %s: slave %d silent %d times in a row; answering 0x0B at once, "
                "probing every %.1f s or more",
                self._name,
                note.slave,
                note.amount,
                self._bus.config.probe_interval,
            )
        elif state is SlaveState.SUSPECT:
            self.fault_log.note(
                f"unit {unit} on line {self._name}",
                "suspect slave",
                "missed an answer; its requests wait behind the others, one at a time",
                level=logging.INFO,
            )
        else:
            log.info("line %s: slave %d answers again", self._name, note.slave)
