"""The line core's vocabulary: requests, actions, the policy it reads, the attempt record.

Everything here is a record or a pure function; no decision is made in this module.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, NamedTuple, Protocol

from .. import pdu as fc
from ..errors import ResponseError
from ..framing import ResponseDecoder
from ..outcome import DiscardReason, LineEvent, Outcome, SlaveState

INFINITY: Final = float("inf")
#: Builds a NamedTuple from a tuple without its Python-level ``__new__``: the actions made
#: once per transaction use it (``Transmit(...)`` elsewhere means the same).
tuple_new: Final = tuple.__new__
#: Distinct request frames kept encoded per line (about 70 kB at most).
FRAME_CACHE_SIZE: Final = 256

#: Frames that are not garbage, just not this answer: discard them and go on waiting.
DISCARD_KINDS: Final = frozenset({
    DiscardReason.UNEXPECTED_UNIT, DiscardReason.UNEXPECTED_FUNCTION, DiscardReason.MISMATCH,
    DiscardReason.UNEXPECTED_TID, DiscardReason.NOISE,
})  # fmt: skip
#: The answer decoders' fault kind for a bad CRC or LRC (noted, never discarded).
BAD_CHECK: Final = "crc"
#: An attempt's fault kind for an answer a foreign master's request may own (``foreign``).
SHARED_ANSWER: Final = "shared_answer"


def answer_signature(request: bytes) -> bytes:
    """What a normal answer to ``request`` looks like without its data.

    Two requests with the same signature cannot be told apart by their answers
    (same function, same byte count, or the same echo); requests whose signatures
    differ can. Function codes whose answer length is unknown: the function alone.
    """
    function = request[0]
    if function in _BYTE_COUNT_BITS and len(request) >= 5:
        return bytes((function, ((((request[3] << 8) | request[4]) + 7) // 8) & 0xFF))
    if function in _BYTE_COUNT_REGISTERS and len(request) >= 5:
        return bytes((function, (2 * ((request[3] << 8) | request[4])) & 0xFF))
    if function in fc.ECHOED_WRITES:
        return fc.write_response(request)
    return bytes((function,))


_BYTE_COUNT_BITS: Final = frozenset({fc.READ_COILS, fc.READ_DISCRETE_INPUTS})
_BYTE_COUNT_REGISTERS: Final = frozenset(
    {fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS, fc.READ_WRITE_MULTIPLE_REGISTERS}
)


class CacheRulePolicy(Protocol):
    """A read-cache rule, as the configuration gives it."""

    @property
    def max_age(self) -> float: ...

    def covers(self, unit: int, function: int, address: int, quantity: int) -> bool: ...


class PollBlockPolicy(Protocol):
    """One block of a line's poll plan, as the configuration gives it (``polling``)."""

    @property
    def unit(self) -> int: ...
    @property
    def slave(self) -> int: ...
    @property
    def function(self) -> int: ...
    @property
    def address(self) -> int: ...
    @property
    def count(self) -> int: ...
    @property
    def every(self) -> float: ...
    @property
    def max_age(self) -> float: ...


class LinePolicy(Protocol):
    """The settings the core needs from one line's configuration (``config.LineConfig``)."""

    @property
    def baudrate(self) -> int: ...
    @property
    def data_bits(self) -> int: ...
    @property
    def parity(self) -> str: ...
    @property
    def stop_bits(self) -> float: ...
    @property
    def retries(self) -> int: ...
    @property
    def retry_unsafe(self) -> bool: ...
    @property
    def broadcast_turnaround(self) -> float: ...
    @property
    def max_queue(self) -> int: ...
    @property
    def max_queue_per_master(self) -> int: ...
    @property
    def max_queue_wait(self) -> float: ...
    @property
    def dead_after(self) -> int: ...
    @property
    def reconnect_after(self) -> int: ...
    @property
    def networked(self) -> bool: ...
    @property
    def probe_interval(self) -> float: ...
    @property
    def probe_max_interval(self) -> float: ...
    @property
    def probe_share(self) -> float: ...
    @property
    def coalesce(self) -> bool: ...
    @property
    def cache(self) -> Sequence[CacheRulePolicy]: ...
    @property
    def polls(self) -> Sequence[PollBlockPolicy]: ...
    @property
    def gap(self) -> float: ...
    @property
    def silence(self) -> float: ...
    @property
    def noisy_deadline(self) -> float: ...
    @property
    def echo(self) -> bool: ...

    @property
    def learn_timeouts(self) -> bool: ...
    @property
    def initial_timeout(self) -> float: ...
    @property
    def max_timeout(self) -> float: ...
    @property
    def slave_timeouts(self) -> Mapping[int, float]: ...
    @property
    def late_answer_window(self) -> float | None: ...
    @property
    def noisy_after(self) -> float | None: ...

    def timeout_for(self, slave: int) -> float: ...

    def late_window_for(self, slave: int) -> float: ...


def no_reply(_pdu: bytes, _outcome: str) -> None:
    """A reply that goes nowhere: a broadcast's, or a request's once it has been answered."""


@dataclass(slots=True, eq=False, init=False)
class LineRequest:
    """One master's request for one slave; ``reply`` is for the driver, never called here."""

    slave: int
    pdu: bytes
    master: Hashable
    reply: Callable[[bytes, Outcome], None]
    broadcast: bool
    enqueued_at: float
    attempts: int  # attempts made so far
    cancelled: bool  # its master left
    answered: bool
    sent: bool  # its frame went on the wire at least once
    single: bool  # one attempt only (it went through the lane: a probe)
    lane_deadline: float
    epoch: int
    order: int  # its place among the line's submissions (set by ``submit``)
    followers: list[LineRequest]
    proof: bool  # the line's own read, sent to prove a lost answer can no longer come
    poll: bool  # the line's own read of a poll block (agent mode)
    counted_change: bool  # counted against poll blocks it may change, until it ends

    def __init__(
        self,
        slave: int,
        pdu: bytes,
        master: Hashable,
        reply: Callable[[bytes, Outcome], None],
        broadcast: bool = False,
    ) -> None:
        # Written out rather than generated by ``dataclass``: the compiled build runs this
        # one natively, where a generated one costs several times more per request.
        self.slave = slave
        self.pdu = pdu
        self.master = master
        self.reply = reply
        self.broadcast = broadcast
        self.enqueued_at = 0.0
        self.attempts = 0
        self.cancelled = False
        self.answered = False
        self.sent = False
        self.single = False
        self.lane_deadline = INFINITY
        self.epoch = 0
        self.order = 0
        self.followers = []
        self.proof = False
        self.poll = False
        self.counted_change = False

    @property
    def wanted(self) -> bool:
        """False when nobody waits for the answer any more."""
        return not self.cancelled or any(not f.cancelled for f in self.followers)


def may_change(request: LineRequest, slave: int) -> bool:
    """True when ``request`` may change what ``slave`` holds: anything but a plain read,
    sent to it or broadcast."""
    return (request.slave == slave or request.broadcast) and request.pdu[0] not in fc.READ_FUNCTIONS


@dataclass(slots=True)
class LineStats:
    """Traffic counts as plain integers (exported at scrape time; the hot path only adds)."""

    frames_sent: int = 0
    frames_received: int = 0
    bytes_written: int = 0
    bytes_read: int = 0
    queue_depth: int = 0


class Transmit(NamedTuple):
    """Write ``frame`` to the line now (the core has checked the quiet time)."""

    frame: bytes
    request: LineRequest
    queue_wait: float
    retry: bool


class Delivery(NamedTuple):
    """The answer for ``request``; ``wire_time`` is negative when no transaction produced it."""

    request: LineRequest
    pdu: bytes
    outcome: Outcome
    wire_time: float


class LateWindow(NamedTuple):
    """A slave's open late-answer window, handed on to the line that replaces this one."""

    slave: int
    until: float
    signatures: frozenset[bytes]  # answers that may still come
    owner: LineRequest | None  # the request whose attempts were lost
    pending: int  # its attempts whose answers may still come


class HeardBus(NamedTuple):
    """What a line heard of other masters, handed on to the line that replaces it."""

    last_master_frame_at: float | None
    last_frame_at: float | None
    shared_until: float  # ``-INFINITY``: not shared
    foreign_frames: int
    heard_master_frames: int
    listening: bool
    pending: tuple[tuple[int, bytes, float, float], ...]  # slave, PDU, heard at, until
    own_echoes: tuple[tuple[bytes, float], ...] = ()  # our echoed writes: frame, until


class Handover(NamedTuple):
    """The wire as a line leaves it to the line that replaces it (``LineCore.handover``)."""

    quiet_since: float  # no frame before this plus the gap (a broadcast's turnaround)
    windows: tuple[LateWindow, ...]
    heard: HeardBus | None = None  # other masters heard (``foreign``)
    framing: str = ""  # the framing its windows' answers would come in (``LineKind``)
    blocks: tuple[KeptBlock, ...] = ()  # the poll blocks' memory (agent mode)


class KeptBlock(NamedTuple):
    """What a poll block knows that the line replacing this one keeps (``polling``)."""

    key: tuple[int, int, int, int]  # slave, function, address, count
    answer: bytes
    polled_at: float
    failing: bool
    due: float
    sent_at: float
    period: float | None
    outcomes: tuple[tuple[Outcome, int], ...]
    served: int


class Note(NamedTuple):
    """An event for metrics and logs."""

    event: LineEvent
    slave: int
    detail: str = ""
    amount: int = 1
    state: SlaveState | None = None


@dataclass(slots=True, eq=False, init=False)
class Attempt:
    """One attempt on the wire. On a pipelined line it also has its transaction id, the
    slave's write epoch when it was sent and the estimate charged then (else -1, 0, 0.0)."""

    request: LineRequest
    decoder: ResponseDecoder
    sent_at: float
    deadline: float
    from_credit: bool
    expected_at: float  # when the answer would have ended with no turnaround at all
    learn_above: float  # an answer after this teaches the learned timing (``complete``)
    silence_at: float
    garbled_at: float
    garbled: ResponseError | None
    heard: bytes  # bytes the answer's decoder took without a verdict yet (``foreign``)
    tid: int
    epoch: int
    charged: float

    def __init__(
        self,
        request: LineRequest,
        decoder: ResponseDecoder,
        sent_at: float,
        deadline: float,
        from_credit: bool,
        expected_at: float,
        learn_above: float,
        tid: int = -1,
        epoch: int = 0,
        charged: float = 0.0,
    ) -> None:
        # Written out, as ``LineRequest``'s: one per transaction.
        self.request = request
        self.decoder = decoder
        self.sent_at = sent_at
        self.deadline = deadline
        self.from_credit = from_credit
        self.expected_at = expected_at
        self.learn_above = learn_above
        self.silence_at = INFINITY
        self.garbled_at = INFINITY
        self.garbled = None
        self.heard = b""
        self.tid = tid
        self.epoch = epoch
        self.charged = charged
