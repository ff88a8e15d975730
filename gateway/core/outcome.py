"""One vocabulary for what became of a request, and for the line's notable events.

Every layer speaks it: the line core decides an ``Outcome``, the TCP side writes the
matching reply, metrics use the values as label values (so the set is fixed and small)
and create every labelled series from these enums.
"""

from __future__ import annotations

from enum import StrEnum

from .reasons import CloseReason as CloseReason  # the reasons belong to this vocabulary
from .reasons import MasterFault as MasterFault
from .reasons import RejectReason as RejectReason


class Outcome(StrEnum):
    """What became of one request from a master; the ``outcome`` label's whole vocabulary."""

    OK = "ok"  # a normal response from the slave
    SLAVE_EXCEPTION = "slave_exception"  # the slave answered with a Modbus exception
    NO_ROUTE = "no_route"  # 0x0A: no line for the unit, the line is down, or it is full
    TARGET_FAILED = "target_failed"  # 0x0B: slave silent, garbled, isolated, or line noisy
    BUSY = "busy"  # 0x06: this master's own queue on the line is full
    REJECTED = "rejected"  # answered locally: a request no slave could accept
    DENIED = "denied"  # refused by the listener's policy (0x01), never sent to the line
    BROADCAST = "broadcast"  # sent to unit 0, no answer expected
    DROPPED = "dropped"  # the master left before its answer was ready
    CACHED = "cached"  # answered from the read cache
    MEMORY = "memory"  # answered from a poll block's memory (agent mode)


class SlaveState(StrEnum):
    """How the line treats one slave address (dead-slave isolation)."""

    UP = "up"  # answers: served in the masters' fair order
    SUSPECT = "suspect"  # missed its last answer: behind the healthy slaves, one at a time
    DOWN = "down"  # missed several in a row: answered 0x0B at once, probed now and then


class BlockState(StrEnum):
    """A poll block's freshness (agent mode), as the status unit and ``/status`` show it."""

    FRESH = "fresh"  # its data is younger than the block's ``max_age``
    STALE = "stale"  # older than ``max_age``, or never polled
    FAILING = "failing"  # its last poll got an exception, a timeout or a garbled answer

    @property
    def code(self) -> int:
        """The status unit's register value: 0 fresh, 1 stale, 2 failing."""
        return _BLOCK_STATE_CODES[self]


_BLOCK_STATE_CODES: dict[BlockState, int] = {
    BlockState.FRESH: 0,
    BlockState.STALE: 1,
    BlockState.FAILING: 2,
}


class LineEvent(StrEnum):
    """Notable events the line core reports for metrics and logs (never per-frame traffic)."""

    TIMEOUT = "timeout"  # an attempt got no answer in time
    CRC_ERROR = "crc_error"  # an answer arrived with a bad CRC
    GARBLED = "garbled"  # something that is no answer arrived and the attempt failed
    RETRY = "retry"  # a request is sent again
    DISCARDED = "discarded"  # bytes or frames thrown away (``reason`` says why)
    SLAVE_STATE = "slave_state"  # a slave changed state (``state`` says to what)
    LINE_NOISY = "line_noisy"  # no usable gap for too long: the queue was answered 0x0B
    LINE_QUIET = "line_quiet"  # a gap appeared again after the line was noisy
    LATE_WINDOW = "late_window"  # a request was held back because of a possible late answer
    PROOF_READ = "proof_read"  # a read of the line's own, sent to prove a lost answer is gone
    RECONNECT = "reconnect"  # close the connection and open it again (``ReconnectReason``)
    COALESCED = "coalesced"  # a read joined an identical queued read
    FOREIGN_MASTER = "foreign_master"  # a request frame this gateway did not send
    LINE_NOT_SHARED = "line_not_shared"  # no foreign master frame heard for ``SHARED_FOR_S``
    SHARED_ANSWER = "shared_answer"  # an answer another master's request may own: not delivered


class ReconnectReason(StrEnum):
    """Why a network line's connection is closed and opened again: the ``reason`` label."""

    OUT_OF_STEP = "out_of_step"  # a frame header no Modbus TCP slave sends
    SILENT = "silent"  # answers missed in a row, nothing heard on it from any slave


class DiscardReason(StrEnum):
    """Why bytes from a line were thrown away: the ``reason`` label's whole vocabulary.

    The line core's own reasons, and the answer decoders' fault kinds
    (``ResponseError.kind``) except a bad CRC or LRC, which is counted on its own.
    """

    LATE = "late"  # nobody was waiting (or a lost answer, after its attempt failed)
    INCOMPLETE = "incomplete"  # half an answer at the timeout
    UNEXPECTED_UNIT = "unexpected_unit"  # another unit's frame
    UNEXPECTED_FUNCTION = "unexpected_function"  # an answer to another function
    MISMATCH = "mismatch"  # the right unit and function, not this request's answer
    SHORT_FRAME = "short_frame"  # shorter than any answer
    OVERSIZE = "oversize"  # longer than any answer may be
    TRAILING_BYTES = "trailing_bytes"  # bytes after a complete answer
    NOISE = "noise"  # bytes in front of the answer
    RESTARTED = "restarted"  # ASCII: ':' inside a frame, a new frame began
    BAD_CHAR = "bad_char"  # ASCII: a character that is not hexadecimal
    UNEXPECTED_TID = "unexpected_tid"  # Modbus TCP: an answer to another transaction
    BAD_HEADER = "bad_header"  # Modbus TCP: a header no slave sends (the stream is out of step)
