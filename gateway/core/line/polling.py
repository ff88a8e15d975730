"""Agent mode's memory: the line's poll plan, the blocks it keeps, and their freshness.

Theory of operation. Each block of the plan is one read (function 1-4, an address range
of one slave) that the line sends itself every ``every`` seconds, before the masters'
waiting requests (``LineCore._pick``). A master's read that lies wholly inside one block
is answered from the block's last answer, byte for byte what the slave sent for those
registers or bits, while that answer is younger than ``max_age``; any other read goes to
the wire. The age of an answer counts from the moment its poll was sent: the slave read
its registers no earlier.

The contract, also after a write. A request that may change a block's table (a write of
any function, a broadcast, a function this module does not know) counts against every
block it may touch from the moment it is submitted until it has ended, and a poll whose
frame went while such a change was outstanding, or before the change was submitted,
proves nothing about the block: masters read from the wire meanwhile, and the block is
polled again as soon as the last change has ended. So a read never gets a value older
than a change submitted before it, wherever the change came from, as long as it passed
through this line.

Exceptions, timeouts and garbled answers are never kept: the block is marked failing and
its last good answer ages out. Only questions and bookkeeping here; the machine decides
when a poll goes and applies what these answer.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Final

from .. import pdu as fc
from ..outcome import BlockState, Outcome
from .records import INFINITY, KeptBlock, LineRequest, PollBlockPolicy

#: The master polls are charged to in the fair queue's records and the trace.
POLLER: Final = "the line's poll plan"
#: The status unit's age register saturates here (also "never polled").
AGE_NEVER: Final = 0xFFFF

#: The table each read function reads, and each write function changes.
_READ_TABLE: Final = {
    fc.READ_COILS: "coils",
    fc.READ_DISCRETE_INPUTS: "discrete_inputs",
    fc.READ_HOLDING_REGISTERS: "holding_registers",
    fc.READ_INPUT_REGISTERS: "input_registers",
}
_BIT_FUNCTIONS: Final = frozenset({fc.READ_COILS, fc.READ_DISCRETE_INPUTS})


def changed_range(pdu: bytes) -> tuple[str, int, int] | None:
    """``(table, first, count)`` a request may change; ``None`` for a plain read.

    A function this module cannot place (diagnostics, file records, a vendor's own)
    changes the whole of every table: ``("*", 0, 65536)``.
    """
    function = pdu[0]
    if function in _READ_TABLE:
        return None
    if len(pdu) >= 3:
        address = (pdu[1] << 8) | pdu[2]
        if function == fc.WRITE_SINGLE_COIL:
            return "coils", address, 1
        if function in (fc.WRITE_SINGLE_REGISTER, fc.MASK_WRITE_REGISTER):
            return "holding_registers", address, 1
        if len(pdu) >= 5:
            count = (pdu[3] << 8) | pdu[4]
            if function == fc.WRITE_MULTIPLE_COILS:
                return "coils", address, count
            if function == fc.WRITE_MULTIPLE_REGISTERS:
                return "holding_registers", address, count
        if function == fc.READ_WRITE_MULTIPLE_REGISTERS and len(pdu) >= 9:
            write_address = (pdu[5] << 8) | pdu[6]
            return "holding_registers", write_address, (pdu[7] << 8) | pdu[8]
    return "*", 0, 65536


@dataclass(slots=True, eq=False)
class PollBlock:
    """One block's memory and bookkeeping."""

    spec: PollBlockPolicy
    table: str
    due: float  # when it is polled next (0.0: at once)
    answer: bytes | None = None  # the slave's last normal answer to the poll (its PDU)
    polled_at: float = -INFINITY  # when the poll that brought ``answer`` was sent
    failing: bool = False  # the last poll ended without a normal answer
    generation: int = 0  # changes submitted so far that may touch the block
    pending: int = 0  # of those, the ones that have not ended
    valid: int = -1  # the generation ``answer`` describes (-1: none)
    poll: LineRequest | None = None  # its poll, waiting or on the wire
    sent_generation: int = -1  # what the poll on the wire can prove (-1: nothing)
    sent_at: float = -INFINITY  # when the last poll's first attempt went
    frame_at: float = -INFINITY  # when the poll's latest attempt went (its answer's time)
    period: float | None = None  # the achieved period, a moving mean
    outcomes: dict[Outcome, int] = field(default_factory=dict)  # polls by outcome
    served: int = 0  # reads answered from it

    @property
    def key(self) -> tuple[int, int, int, int]:
        spec = self.spec
        return spec.slave, spec.function, spec.address, spec.count

    def covers(self, function: int, address: int, count: int) -> bool:
        spec = self.spec
        return (
            function == spec.function
            and address >= spec.address
            and address + count <= spec.address + spec.count
        )

    def touched_by(self, table: str, first: int, count: int) -> bool:
        spec = self.spec
        return (table == "*" or table == self.table) and (
            first < spec.address + spec.count and spec.address < first + count
        )

    def usable(self, now: float) -> bool:
        """Its answer may serve a read now: no change outstanding or since, young enough."""
        return (
            self.answer is not None
            and self.pending == 0
            and self.valid == self.generation
            and now - self.polled_at <= self.spec.max_age
        )

    def age(self, now: float) -> float | None:
        return None if self.answer is None else max(0.0, now - self.polled_at)

    def state(self, now: float) -> BlockState:
        """Fresh, stale (older than ``max_age``, or never polled) or failing. A block
        waiting for its poll after a write stays fresh while its age allows."""
        if self.failing:
            return BlockState.FAILING
        age = self.age(now)
        if age is None or age > self.spec.max_age:
            return BlockState.STALE
        return BlockState.FRESH

    def status_registers(self, now: float) -> tuple[int, int]:
        """The status unit's two registers: age in tenths of a second, and state."""
        age = self.age(now)
        tenths = AGE_NEVER if age is None else min(AGE_NEVER, int(age * 10.0))
        return tenths, self.state(now).code


class PollPlan:
    """The blocks of one line, by slave, and the questions the machine asks of them."""

    def __init__(self, specs: Sequence[PollBlockPolicy] = (), now: float = 0.0) -> None:
        self.blocks: list[PollBlock] = []
        self.by_slave: dict[int, list[PollBlock]] = {}
        self.next_due = INFINITY
        self.stopped = False  # the line stops: no more polls (``stop``)
        #: Changes submitted that have not ended, by id: a block added meanwhile counts them.
        self.changes: dict[int, LineRequest] = {}
        self.configure(specs, now)

    def configure(self, specs: Sequence[PollBlockPolicy], now: float) -> None:
        """Take a new plan: a block whose slave, function and range are unchanged keeps
        its memory and schedule; new blocks are due at once."""
        old = {block.key: block for block in self.blocks}
        blocks: list[PollBlock] = []
        for spec in specs:
            key = (spec.slave, spec.function, spec.address, spec.count)
            block = old.pop(key, None)
            if block is None:
                block = PollBlock(spec, _READ_TABLE[spec.function], now)
                for change in self.changes.values():  # outstanding: it proves nothing yet
                    if change.broadcast or (
                        change.slave == spec.slave
                        and block.touched_by(*(changed_range(change.pdu) or ("", 0, 0)))
                    ):
                        block.generation += 1
                        block.pending += 1
            else:
                if spec.every != block.spec.every:  # a new period applies from the last poll
                    waiting = block.poll is not None  # then ``due`` is already the next one's
                    last = block.due - block.spec.every if waiting else block.sent_at
                    block.due = min(block.due, last + spec.every)
                block.spec = spec
            blocks.append(block)
        self.blocks = blocks
        self.by_slave = {}
        for block in blocks:
            self.by_slave.setdefault(block.spec.slave, []).append(block)
        self._update_due()

    def handover(self) -> tuple[KeptBlock, ...]:
        """The memory the line replacing this one keeps: answers that still describe their
        block (no change outstanding or since), with each block's schedule and counters."""
        return tuple(
            KeptBlock(
                block.key,
                block.answer,
                block.polled_at,
                block.failing,
                0.0 if block.poll is not None else block.due,
                block.sent_at,
                block.period,
                tuple(block.outcomes.items()),
                block.served,
            )
            for block in self.blocks
            if block.answer is not None and block.pending == 0 and block.valid == block.generation
        )

    def take_over(self, kept: Sequence[KeptBlock]) -> None:
        """Start from the memory of the line this one replaces (``handover``), for the
        blocks of this plan with the same slave, function and range."""
        by_key = {block.key: block for block in kept}
        for block in self.blocks:
            old = by_key.get(block.key)
            if old is None:
                continue
            block.answer, block.polled_at, block.failing = old.answer, old.polled_at, old.failing
            block.due, block.sent_at, block.period = old.due, old.sent_at, old.period
            block.outcomes, block.served = dict(old.outcomes), old.served
            block.valid = block.generation
        self._update_due()

    def _update_due(self) -> None:
        if self.stopped:
            self.next_due = INFINITY
            return
        self.next_due = min(
            (block.due for block in self.blocks if block.poll is None), default=INFINITY
        )

    def stop(self) -> None:
        """The line stops: nothing more is polled (what is on the wire finishes)."""
        self.stopped = True
        self.next_due = INFINITY

    # -- masters' requests ---------------------------------------------------------------

    def serve(self, slave: int, pdu: bytes, now: float) -> bytes | None:
        """The answer to read ``pdu`` from memory, ``None`` when it must go to the wire."""
        blocks = self.by_slave.get(slave)
        if blocks is None or len(pdu) != 5:
            return None
        function = pdu[0]
        address = (pdu[1] << 8) | pdu[2]
        count = (pdu[3] << 8) | pdu[4]
        for block in blocks:
            if block.covers(function, address, count) and block.usable(now):
                block.served += 1
                return _slice(block, address, count)
        return None

    def change_submitted(self, request: LineRequest) -> bool:
        """Count ``request`` (not a plain read) against the blocks it may touch, and
        against blocks a reload adds before it ends; ``change_ended`` must follow."""
        for block in self._touched(request):
            block.generation += 1
            block.pending += 1
        self.changes[id(request)] = request
        return True

    def change_ended(self, request: LineRequest) -> None:
        """A change counted by ``change_submitted`` ended: once none is outstanding, the
        block is polled again at once."""
        self.changes.pop(id(request), None)
        for block in self._touched(request):
            block.pending -= 1
            if block.pending == 0 and block.poll is None:
                block.due = 0.0
        self._update_due()

    def _touched(self, request: LineRequest) -> list[PollBlock]:
        if request.broadcast:
            return list(self.blocks)
        blocks = self.by_slave.get(request.slave)
        if blocks is None:
            return []
        changed = changed_range(request.pdu)
        if changed is None:
            return []
        table, first, count = changed
        return [block for block in blocks if block.touched_by(table, first, count)]

    # -- the plan's own polls ------------------------------------------------------------

    def due(self, now: float) -> Iterable[PollBlock]:
        """Blocks whose poll is due and not yet waiting or on the wire, in plan order."""
        if now < self.next_due:
            return ()
        return [block for block in self.blocks if block.poll is None and block.due <= now]

    def poll_made(self, block: PollBlock, request: LineRequest, now: float) -> None:
        """``request`` polls ``block`` now; the next poll is due one period after the
        planned time (not after this one: the plan keeps its pace), or one period from now
        when it fell a whole period behind."""
        block.poll = request
        spec = block.spec
        due = block.due + spec.every if block.due > 0.0 else now + spec.every
        block.due = due if due > now else now + spec.every
        self._update_due()

    def skipped(self, block: PollBlock, now: float) -> None:
        """The poll could not be placed now (its isolated slave's lane place is taken):
        the next is due one period later."""
        block.due = now + block.spec.every
        self._update_due()

    def sent(self, block: PollBlock, now: float) -> None:
        """The poll's frame goes now: what its answer can prove is fixed here."""
        poll = block.poll
        if poll is not None and poll.attempts <= 1:  # a first attempt: the achieved period
            if block.sent_at > -INFINITY:
                interval = now - block.sent_at
                period = block.period
                block.period = interval if period is None else 0.8 * period + 0.2 * interval
            block.sent_at = now
        block.sent_generation = block.generation if block.pending == 0 else -1
        block.frame_at = now

    def ended(self, block: PollBlock, response: bytes, outcome: Outcome) -> None:
        """The poll ended: keep a normal answer that proves the block's current state,
        mark anything else failing; poll again at once when the answer proved nothing."""
        block.poll = None
        block.outcomes[outcome] = block.outcomes.get(outcome, 0) + 1
        if outcome is Outcome.OK:
            block.failing = False
            if block.sent_generation >= 0 and block.sent_generation == block.generation:
                block.answer = response
                block.polled_at = block.frame_at
                block.valid = block.generation
            elif block.pending == 0:
                block.due = 0.0  # a change ran meanwhile: this answer may predate it
        elif outcome is not Outcome.DROPPED:  # dropped: the line was reopened, not failed
            block.failing = True
        self._update_due()

    def block_of(self, request: LineRequest) -> PollBlock | None:
        for block in self.blocks:
            if block.poll is request:
                return block
        return None


def _slice(block: PollBlock, address: int, count: int) -> bytes:
    """The part of ``block``'s answer for ``count`` items from ``address``, encoded as the
    slave encodes an answer to that read."""
    answer = block.answer
    assert answer is not None
    offset = address - block.spec.address
    function = answer[0]
    if block.spec.function in _BIT_FUNCTIONS:
        data = answer[2:]
        out = bytearray((count + 7) // 8)
        for index in range(count):
            bit = offset + index
            if data[bit >> 3] >> (bit & 7) & 1:
                out[index >> 3] |= 1 << (index & 7)
        return bytes((function, len(out))) + bytes(out)
    start = 2 + 2 * offset
    return bytes((function, 2 * count)) + answer[start : start + 2 * count]
