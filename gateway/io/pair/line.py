"""A line's part in a redundancy pair: the role its driver holds (``io.bus.LineRole``).

The driver asks it right before every frame and tells it what the line hears; it hands
both on to the pair (``role.Pair``): the lease check, and the bus's evidence (any byte
shows the bus busy; a master frame this gateway did not send makes an active one step
down). The pair, in turn, stands the line by or activates it (``Bus.stand_by``,
``Bus.activate``) and reads it for a keep-alive (``keepalive_slave``).
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from ..line.bus import Bus


class Forwarding(Protocol):
    def cancel(self, master: Hashable) -> None: ...


class PairSide(Protocol):
    """What a line's role asks of the pair (``role.Pair``), defined here so that this
    module does not import the role machine's module, which imports it."""

    @property
    def forwarder(self) -> Forwarding: ...
    def may_transmit(self) -> bool: ...
    def master_frame_heard(self) -> None: ...
    def frame_heard(self) -> None: ...


class PairedLine:
    """The role a paired gateway's line plays (``LineRole``): what it asks and hears goes
    to the pair."""

    #: The port opens driving nothing (RTS, DTR, RS485 receive): the bus may be the peer's.
    quiet_open = True

    def __init__(self, pair: PairSide) -> None:
        self._pair = pair

    def may_transmit(self) -> bool:
        """The lease check before every frame."""
        return self._pair.may_transmit()

    def heard(self, master_frame: bool) -> None:
        if master_frame:
            self._pair.master_frame_heard()
        else:
            self._pair.frame_heard()

    def cancel(self, master: Hashable) -> None:
        """``master`` left: its forwarded requests are dropped and its link to the peer closed."""
        self._pair.forwarder.cancel(master)


def keepalive_slave(bus: Bus) -> int:
    """A slave to read for a keep-alive: the one heard answering this gateway most
    recently, else one heard answering the peer (its timing was learned), else the
    line's first unit (0: none)."""
    heard = [(t.last_seen, slave) for slave, t in bus.tally.slaves.items() if t.last_seen]
    if heard:
        return max(heard)[1]
    learned = bus.learned_timeouts(bus.config.units)
    if learned:
        return min(learned)
    return bus.config.units[0] if bus.config.units else 0
