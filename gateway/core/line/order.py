"""Read-after-write order: questions about what one master's request must not pass.

Theory of operation. One master's requests to one slave keep read-after-write order: a
request that may change the slave (a write, any code but a plain read; a broadcast
changes every slave) passes none of its master's earlier requests to it, and nothing
of that master passes it, also through the isolated slaves' lane or inside another
master's read it joined. A read joins another master's identical queued read only when
no change of its own master to that slave waits (the other read may go first, and its
answer would predate the change); the cache keeps no answer older than a change still
to run.

Only questions here, over the other parts' state; nothing changes.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable
from typing import Protocol

from .fair_queue import FairQueue
from .health import ProbeLane
from .records import LineRequest, may_change
from .sharing import ReadSharing


class Outstanding(Protocol):
    """What the rules ask of the wire (``wire.Wire``): the requests on it."""

    def requests(self) -> list[LineRequest]: ...

    def overtakable(self) -> list[LineRequest]: ...


class OrderRules:
    """The ordering questions the machine and the wires ask."""

    def __init__(
        self,
        queue: FairQueue,
        lane: ProbeLane,
        sharing: ReadSharing,
        retries: deque[LineRequest],
        wire: Outstanding,
    ) -> None:
        self.queue = queue
        self.lane = lane
        self.sharing = sharing
        self.retries = retries
        self.wire = wire

    def leaders(self) -> list[LineRequest]:
        """Reads that others joined and that still wait: queued, or back in the isolated
        slaves' lane after a failed attempt (their followers still wait with them)."""
        return self.sharing.leaders(list(self.lane.requests.values()))

    def carriers(self) -> list[LineRequest]:
        """Every request whose answer others that joined it still wait for: the waiting
        leaders, the retries and the attempts on the wire."""
        carriers = self.leaders()
        carriers.extend(self.retries)
        carriers.extend(self.wire.requests())
        return carriers

    def change_pending(self, master: Hashable, slave: int) -> bool:
        """True while a request of ``master`` that may change ``slave`` waits for the line
        (or is outstanding where a later send may overtake it)."""
        record = self.queue.masters.get(master)
        if record is not None and any(may_change(r, slave) for r in record.queue):
            return True
        for request in [*self.retries, *self.wire.overtakable()]:
            if request.master == master and may_change(request, slave):
                return True
        return any(r.master == master and may_change(r, slave) for r in self.lane.requests.values())

    def change_waits_for(self, slave: int) -> bool:
        """True while a request that may change ``slave`` waits for the line: queued, in
        the lane, due for a retry, or outstanding where it may run after a read's answer."""
        waiting = [*self.retries, *self.wire.overtakable()]
        waiting.extend(self.lane.requests.values())
        waiting.extend(self.queue.waiting())
        return any(may_change(request, slave) for request in waiting)

    def broadcast_held(self, master: Hashable, broadcast: LineRequest) -> bool:
        """True while a read ``master`` submitted before ``broadcast`` has not gone: in the
        isolated slaves' lane, or joined to another master's read that still waits."""
        for request in self.lane.requests.values():
            if request.master == master and request.order < broadcast.order:
                return True
        for leader in self.leaders():
            for follower in leader.followers:
                if (
                    follower.master == master
                    and follower.order < broadcast.order
                    and not follower.cancelled
                ):
                    return True
        return False

    def behind_broadcast(self, request: LineRequest) -> bool:
        """True while a broadcast its master submitted before ``request`` waits (a request
        from the lane must not pass it)."""
        master = self.queue.masters.get(request.master)
        return master is not None and any(
            queued.broadcast and queued.order < request.order for queued in master.queue
        )

    def held_by_joined(self, master: Hashable, write: LineRequest) -> bool:
        """True while a read ``master`` sent before ``write`` waits inside another master's
        read (it joined it; queued, or back in the lane): the write must not overtake it."""
        for leader in self.leaders():
            if leader.slave == write.slave and leader.epoch < write.epoch:
                for follower in leader.followers:
                    if follower.master == master and not follower.cancelled:
                        return True
        return False
