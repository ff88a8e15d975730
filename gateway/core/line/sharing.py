"""Read sharing: identical reads coalesced into one transaction, and the read cache.

Theory of operation. A read joins another master's identical queued read (the
*leader*) only while no change to that slave was submitted after the leader: each
slave has a write epoch, bumped by every request that may change it (a broadcast
bumps every slave's), and a leader carries the epoch it was queued under. A leader is
open to joiners until its frame goes on the wire. The cache keeps a read's answer for
its rule's ``max_age``; a change to the slave empties the slave's entries, a broadcast
empties the cache.

This part keeps the leaders, epochs and answers; the machine (``machine.LineCore``)
decides when a read joins, is answered from the cache, or is stored.
"""

from __future__ import annotations

from collections.abc import Sequence

from .records import CacheRulePolicy, LineRequest

ReadKey = tuple[int, bytes]


class ReadSharing:
    """Open leaders, write epochs and cached answers."""

    def __init__(self) -> None:
        self.open_reads: dict[ReadKey, LineRequest] = {}
        #: Queued reads that others joined, until sent or answered; a read back in the
        #: queue after a failed attempt (from the lane) is listed again.
        self.joined: dict[LineRequest, None] = {}
        self.write_epoch: dict[int, int] = {}
        self.broadcast_epoch = 0
        self.cache: dict[ReadKey, tuple[float, bytes]] = {}

    def epoch(self, slave: int) -> int:
        """Changes submitted for ``slave`` so far (its own and broadcasts)."""
        return self.write_epoch.get(slave, 0) + self.broadcast_epoch

    def broadcast(self) -> None:
        """A broadcast writes to every slave: nothing read before it may be shared after."""
        self.broadcast_epoch += 1
        self.cache.clear()

    def change(self, slave: int) -> None:
        """A request that may change ``slave``: later reads must not share earlier answers."""
        self.write_epoch[slave] = self.write_epoch.get(slave, 0) + 1
        if self.cache:
            for key in [key for key in self.cache if key[0] == slave]:
                del self.cache[key]

    def cached(self, key: ReadKey, now: float) -> bytes | None:
        """A fresh cached answer for ``key``."""
        entry = self.cache.get(key)
        if entry is not None and now <= entry[0]:
            return entry[1]
        return None

    def leader(self, key: ReadKey, epoch: int) -> LineRequest | None:
        """The open read ``key`` a read under ``epoch`` may join."""
        leader = self.open_reads.get(key)
        return leader if leader is not None and leader.epoch == epoch else None

    def join(self, leader: LineRequest, follower: LineRequest) -> None:
        leader.followers.append(follower)
        self.joined[leader] = None

    def close(self, request: LineRequest) -> None:
        """From now on (its frame goes on the wire) no other read may join ``request``."""
        key = (request.slave, request.pdu)
        if self.open_reads.get(key) is request:
            del self.open_reads[key]
        self.joined.pop(request, None)

    def leaders(self, lane: Sequence[LineRequest]) -> list[LineRequest]:
        """Reads that others joined and that still wait: queued, or back in the lane."""
        leaders = list(self.joined)
        leaders.extend(r for r in lane if r.followers)
        return leaders

    def forget_open(self) -> None:
        """The queue was taken: no read is open to joiners any more."""
        self.open_reads.clear()
        self.joined.clear()

    def store(
        self, request: LineRequest, response: bytes, now: float, rules: Sequence[CacheRulePolicy]
    ) -> None:
        """Keep ``response`` for the first rule that covers ``request``."""
        pdu = request.pdu
        address = (pdu[1] << 8) | pdu[2]
        quantity = (pdu[3] << 8) | pdu[4]
        for rule in rules:
            if rule.covers(request.slave, pdu[0], address, quantity):
                self.cache[(request.slave, pdu)] = (now + rule.max_age, response)
                return
