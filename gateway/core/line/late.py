"""Late-answer windows: after an attempt fails, its answer may still come.

Theory of operation. For a slave's window no request that could be confused with the
lost one (same answer signature: ``records.answer_signature``) is sent to it; the
lost request's own retry is exempt (any answer to it is its answer). A window lasts
until proof that the lost answer can no longer come, however late the slave is
(``late_answer_window``, when set, bounds it in seconds instead). Proof is one of:

* the answers of every lost attempt of its owner have arrived;
* the slave answered a request sent after the loss that could not be confused with it
  (a serial slave answers one request at a time, in order: nothing more will follow).

When a request waits for such proof and nothing else would bring it, the line sends a
*proof read* of its own (``proof_pdu``): a read the slave answered before, or the same
function at the same address with another count, so that its normal answer cannot be
taken for any answer the window awaits. Its answer goes to nobody. A proof answered by
an exception that looks like a lost one proves nothing; after ``MAX_INCONCLUSIVE`` of
them the window closes after ``2 x max_timeout`` instead, as it does at once for a slave
that never answered anything (a proof read would meet its silence too) or when no read
of the slave is known.

This part keeps the windows and recognises lost answers in the line's bytes; the
machine (``machine.LineCore``) opens windows, notes them and acts on what arrives.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from .. import pdu as fc
from ..errors import ResponseError
from ..framing import ResponseDecoder
from .records import INFINITY, LateWindow, LineRequest, answer_signature

NewDecoder = Callable[[int, bytes], ResponseDecoder]

#: Proof reads answered by an exception that proves nothing, before a window gives up
#: on proof and closes after a time instead.
MAX_INCONCLUSIVE: Final = 2
#: The reads a proof may be (they change nothing): coils, inputs, registers.
PROOF_FUNCTIONS: Final = frozenset(
    {fc.READ_COILS, fc.READ_DISCRETE_INPUTS, fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS}
)


def proof_pdu(signatures: set[bytes], known_read: bytes | None, lost: bytes | None) -> bytes | None:
    """A read whose normal answer cannot be taken for any answer in ``signatures``: the
    slave's ``known_read`` (a read it answered normally) if it differs, else that read's
    function and address (or the lost request's, when it is a read) with the smallest
    count whose answer length differs; ``None`` when no read is known."""
    if known_read is not None and answer_signature(known_read) not in signatures:
        return known_read
    base = known_read if known_read is not None else lost
    if base is None or base[0] not in PROOF_FUNCTIONS or len(base) < 5:
        return None
    function = base[0]
    bits = function in (fc.READ_COILS, fc.READ_DISCRETE_INPUTS)
    for step in range(8):
        count = 8 * step + 1 if bits else step + 1
        pdu = bytes((function, base[1], base[2], count >> 8, count & 0xFF))
        if answer_signature(pdu) not in signatures:
            return pdu
    return None


@dataclass(slots=True, eq=False)
class Window:
    """One slave's open window."""

    until: float = 0.0
    signatures: set[bytes] = field(default_factory=set)  # answers that may still come
    owner: LineRequest | None = None
    decoder: ResponseDecoder | None = None  # recognises the lost answer itself
    pending: int = 0  # the owner's attempts whose answers may still come
    sent_at: float | None = None  # when the owner's latest lost attempt was sent
    proof: LineRequest | None = None  # the proof read sent and not yet ended
    inconclusive: int = 0  # proof reads answered by an exception that proved nothing


class LateWindows:
    """The open windows, by slave."""

    def __init__(self, new_decoder: NewDecoder) -> None:
        self.windows: dict[int, Window] = {}
        self.new_decoder = new_decoder
        #: Slaves whose windows hold a request back and wait for proof (``holds``).
        self.wanted: set[int] = set()

    def open(
        self, slave: int, request: LineRequest, until: float, sent_at: float | None = None
    ) -> None:
        """The slave's answer to ``request`` (its attempt sent at ``sent_at``) may still come
        until ``until`` (or later)."""
        window = self.windows.get(slave)
        if window is None:
            window = self.windows[slave] = Window()
        window.until = max(window.until, until)
        window.signatures.add(answer_signature(request.pdu))
        if window.proof is request:
            window.proof = None  # the proof read failed: another may be sent
        if window.owner is request:
            window.pending += 1  # another attempt of it whose answer may still come
        else:
            # Answers come in order: the new owner's come after any earlier request's.
            window.owner = request
            window.decoder = self.new_decoder(slave, request.pdu)
            window.pending = 1
        if window.sent_at is None or (sent_at is not None and window.pending == 1):
            window.sent_at = sent_at

    def keep(self, handed: LateWindow) -> None:
        """A window handed on by the line this one replaces."""
        window = self.windows.get(handed.slave)
        if window is None:
            window = self.windows[handed.slave] = Window()
        window.until = max(window.until, handed.until)
        window.signatures |= handed.signatures
        owner = handed.owner
        window.owner = owner
        window.decoder = None if owner is None else self.new_decoder(handed.slave, owner.pdu)
        window.pending = handed.pending

    def handover(self) -> list[LateWindow]:
        return [
            LateWindow(slave, w.until, frozenset(w.signatures), w.owner, w.pending)
            for slave, w in self.windows.items()
        ]

    def lost_attempts(self) -> dict[int, tuple[float, int]]:
        """By slave: when its window owner's first lost attempt went, and its function."""
        return {
            slave: (w.sent_at, w.owner.pdu[0])
            for slave, w in self.windows.items()
            if w.sent_at is not None and w.owner is not None
        }

    def close(self, slave: int) -> None:
        del self.windows[slave]
        self.wanted.discard(slave)

    def owners(self) -> list[tuple[int, bytes]]:
        """(slave, PDU) of each window's lost request: answers to them are ours, not
        another master's (``foreign``)."""
        return [
            (slave, window.owner.pdu)
            for slave, window in self.windows.items()
            if window.owner is not None
        ]

    def holds(self, request: LineRequest, now: float) -> bool:
        """True when ``request`` could be confused with a lost answer still on its way."""
        window = self.windows.get(request.slave)
        if (
            window is None
            or now >= window.until
            or request is window.owner
            or answer_signature(request.pdu) not in window.signatures
        ):
            return False
        if window.until == INFINITY and window.proof is None:
            self.wanted.add(request.slave)  # held until proof: ask for a proof read
        return True

    def ends_on(self, slave: int, request: LineRequest, response: bytes) -> bool | None:
        """``slave`` answered ``request`` (not the owner) with ``response`` during its
        window: ``True`` when the window ends (a normal answer: the slave is done),
        ``False`` when an exception that looks like the lost one's reopens it for
        ``request``, ``None`` when nothing changes."""
        window = self.windows.get(slave)
        if window is None or request is window.owner:
            return None
        if not response[0] & fc.EXCEPTION_FLAG:
            return True
        if request.pdu[0] in {signature[0] for signature in window.signatures}:
            return False
        return None

    def expired(self, now: float) -> list[int]:
        return [s for s, w in self.windows.items() if now >= w.until]

    def earliest(self) -> float:
        when = INFINITY
        for window in self.windows.values():
            when = min(when, window.until)
        return when

    def arrived(self, slave: int) -> bool:
        """A lost attempt's answer came: ``True`` when that was the last one (closed)."""
        window = self.windows[slave]
        window.pending -= 1
        if window.pending <= 0:
            self.close(slave)
            return True
        return False

    def watch(self, data: bytes) -> list[int]:
        """Bytes while nothing is on the wire: the slaves whose lost answers they hold,
        once per answer (the windows of the last ones close)."""
        found: list[int] = []
        for slave, window in list(self.windows.items()):
            decoder = window.decoder
            if decoder is None:
                continue
            chunk = data
            while True:
                try:
                    frame = decoder.feed(chunk)
                except ResponseError:
                    chunk = decoder.leftover  # what followed the bad frame may be the answer
                    decoder.reset()
                    if chunk:
                        continue
                    break
                if frame is None:
                    if decoder.waits_for_silence:
                        decoder.reset()  # noise with no length to wait for: start afresh
                    break
                chunk = decoder.leftover
                decoder.reset()
                found.append(slave)
                if self.arrived(slave) or not chunk:
                    break
        return found

    def is_lost_answer(self, frame: bytes) -> int | None:
        """An intact frame the attempt on the wire discarded: the slave whose lost answer
        it is (its window counts it), else ``None``."""
        slave = frame[0]
        window = self.windows.get(slave)
        if window is None or window.owner is None:
            return None
        try:
            answer = self.new_decoder(slave, window.owner.pdu).feed(frame)
        except ResponseError:
            return None
        if answer is None:
            return None
        self.arrived(slave)
        return slave
