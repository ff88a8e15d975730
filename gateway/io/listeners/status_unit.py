"""The status unit as listeners see it: a line of its own that answers at once.

The routing table (``spine.Router``) routes ``polling.status_unit`` to this object as it
routes a unit to a ``Bus``, so every listener's admission and submit path (Modbus TCP,
TLS, RTU over TCP, serial slave) serves it unchanged: the access rules, the gateway's
refusals, validation, the audit log, the trace and ``requests_total`` (under line
``status``) hold for it as for any unit. ``core.status_unit`` makes the answer; this
only reads the lines' blocks and the clock, and hands the answer back within ``submit``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence

from ...core.line import LineRequest, no_reply
from ...core.outcome import Outcome
from ...core.pdu import EXCEPTION_FLAG
from ...core.status_unit import STATUS_LINE, BlockFreshness, status_answer
from ...metrics import GatewayMetrics


class StatusUnit:
    """The status unit's line: every request is answered in ``submit``, none waits."""

    up = True  #: nothing to open: it takes broadcasts never, requests always

    def __init__(
        self, blocks: Callable[[], Sequence[BlockFreshness]], metrics: GatewayMetrics
    ) -> None:
        self.name = STATUS_LINE
        self._blocks = blocks  # every line's blocks in configuration order, read per request
        #: The latency series of its answers, as for a line (line ``status``).
        self.request_duration = metrics.request_duration_for(STATUS_LINE)

    def submit(self, request: LineRequest) -> bool:
        """Answer ``request`` now: the registers, or the exception ``status_answer`` gives
        (counted as the unit's own answer, ``slave_exception``)."""
        answer = status_answer(request.pdu, self._blocks(), time.monotonic())
        outcome = Outcome.SLAVE_EXCEPTION if answer[0] & EXCEPTION_FLAG else Outcome.OK
        request.answered = True
        reply, request.reply = request.reply, no_reply  # answered once, as a line does
        reply(answer, outcome)
        return True

    def cancel(self, master: Hashable) -> None:
        """Nothing of ``master``'s ever waits here."""
