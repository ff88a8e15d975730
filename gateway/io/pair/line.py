"""A line's part in a redundancy pair (``io.pair``): where its requests go, what it hears.

``Bus`` is built on it. While the gateway stands by, the line sends nothing (its core
paused, listening: what it hears still teaches its timing) and every request goes to the
active peer; while active, the line works as a line of a gateway alone. A reload that
reopens the line redirects its requests to the line that replaced it the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from ...config import LineConfig
from ...core.line import LineCore, LineRequest
from ..tally import LineTally

if TYPE_CHECKING:
    from ..bus import Bus
    from .role import Pair


class LineRole:
    """The redirect of a line's requests, and its evidence for the pair."""

    config: LineConfig
    tally: LineTally
    _core: LineCore
    _idle: bool

    def _pump(self, not_before: float = 0.0) -> None: ...

    def _init_role(self) -> None:
        self._successor: Bus | None = None
        #: Where requests go instead of this line: the successor, or the active peer while
        #: this gateway stands by (``stand_by``).
        self._redirect: Callable[[LineRequest], bool] | None = None
        #: The redundancy pair this gateway belongs to, ``None`` for a gateway alone.
        self.pair: Pair | None = None
        self.quiet_open = False  #: open the port driving nothing (RTS, DTR, RS485 receive)
        #: Paused because the lease check refused a frame (``lease_refused``).
        self.refused_by_lease = False

    @property
    def successor(self) -> Bus | None:
        """The line that replaced this one (``hand_over``): requests go there from now on."""
        return self._successor

    @successor.setter
    def successor(self, bus: Bus) -> None:
        self._successor = bus
        self._redirect = bus.submit

    def stand_by(self, forward: Callable[[LineRequest], bool]) -> None:
        """This gateway stands by: send nothing, forward every request (those queued too) to
        the active peer; the transaction on the wire, if any, finishes."""
        core = self._core
        core.pause(time.monotonic())
        core.set_listening(True)
        if self._successor is None:
            self._redirect = forward
        self._pump()
        for request in core.take_queued():
            forward(request)

    def activate(self) -> None:
        """This gateway is active: the line takes its masters' requests and transmits."""
        if self._successor is None:
            self._redirect = None
        self.refused_by_lease = False
        core = self._core
        core.set_listening(False)
        core.resume(time.monotonic())
        self._pump()

    def lease_refused(self) -> None:
        """The lease lapsed between the core's choice of a frame and its write (the frame
        is not written): the line sends nothing more, and what the core holds on the wire,
        never written, is answered 0x0A now, not 0x0B after its timeout, and not charged
        to its slave's health. The pair stands the line by next (``Pair.may_transmit``),
        where what waits goes to the peer; ``activate`` resumes it."""
        self.refused_by_lease = True
        now = time.monotonic()
        core = self._core
        core.pause(now)
        core.abandon(now)

    @property
    def idle(self) -> bool:
        """Nothing waits and nothing is on the wire."""
        return self._idle

    def heard_slave(self) -> int:
        """A slave to read for a keep-alive: the one heard answering this gateway most
        recently, else one heard answering the peer (its timing was learned), else the
        line's first unit (0: none)."""
        heard = [(t.last_seen, slave) for slave, t in self.tally.slaves.items() if t.last_seen]
        if heard:
            return max(heard)[1]
        learned = self._core.timing.by_slave(self.config.units)
        if learned:
            return min(learned)
        return self.config.units[0] if self.config.units else 0

    def hear_paired(self, data: bytes, now: float) -> None:
        """Bytes came in on a paired gateway's line: the core takes them, then the pair its
        evidence. Any byte shows the bus busy; a master frame this gateway did not send
        (``last_master_frame_at`` moved) makes an active one step down."""
        assert self.pair is not None
        core = self._core
        masters = core.last_master_frame_at
        core.receive(data, now)
        self._pump()
        if core.last_master_frame_at != masters:
            self.pair.master_frame_heard()
        else:
            self.pair.frame_heard()
