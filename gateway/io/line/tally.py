"""What each slave of a line was asked and answered, for the status page.

``Bus`` counts every answer it hands back to a master here (one dictionary look-up
per transaction): the requests, the exception codes the slave returned and when it was
last heard. Timeouts and CRC errors are counted by the line's metrics already. When is
stamped with the monotonic clock the line already read for the answer's event, and made
wall-clock time only when the status page asks (``wall_clock``): no clock read per answer.
"""

from __future__ import annotations

import time

from ...core.outcome import Outcome


class SlaveTally:
    """One slave's counts since the line was opened."""

    __slots__ = ("exceptions", "last_seen", "requests")

    def __init__(self) -> None:
        self.requests = 0
        self.exceptions: dict[int, int] = {}
        self.last_seen: float | None = None  # ``time.monotonic()`` of the last answer


class LineTally:
    """Every slave's tally on one line."""

    __slots__ = ("slaves",)

    def __init__(self) -> None:
        self.slaves: dict[int, SlaveTally] = {}

    def count(
        self,
        slave: int,
        pdu: bytes,
        outcome: Outcome,
        now: float | None = None,
        poll: bool = False,
    ) -> None:
        """One answer went back to a master (a slave's, or the gateway's own 0x0A/0x0B),
        heard at ``now`` (``time.monotonic()``; read here when not given). The answer to
        one of the line's own polls (agent mode, ``poll``) is no master's request: it only
        says when the slave was last heard (its block counts it)."""
        tally = self.slaves.get(slave)
        if tally is None:
            tally = self.slaves[slave] = SlaveTally()
        if outcome is Outcome.OK or outcome is Outcome.SLAVE_EXCEPTION:
            tally.last_seen = time.monotonic() if now is None else now
        if poll:
            return
        tally.requests += 1
        if outcome is Outcome.SLAVE_EXCEPTION:
            code = pdu[1] if len(pdu) > 1 else 0
            tally.exceptions[code] = tally.exceptions.get(code, 0) + 1


def wall_clock(seen: float | None) -> float | None:
    """A ``last_seen`` stamp (``time.monotonic()``) as wall-clock seconds, for the status page."""
    return None if seen is None else time.time() - (time.monotonic() - seen)
