"""Late-answer windows: after an attempt fails, its answer may still come.

Theory of operation. For a slave's window no request that could be confused with the
lost one (same answer signature: ``records.answer_signature``) is sent to it; the
lost request's own retry is exempt (any answer to it is its answer). The window
closes at its end, or early once the slave answers a request sent after the loss that
could not be confused with it, or once the answers of every lost attempt of its owner
have arrived (a slave answers one request at a time: nothing more will follow).

This part keeps the windows and recognises lost answers in the line's bytes; the
machine (``machine.LineCore``) opens windows, notes them and acts on what arrives.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from .. import pdu as fc
from ..errors import ResponseError
from ..framing import ResponseDecoder
from .records import INFINITY, LateWindow, LineRequest, answer_signature

NewDecoder = Callable[[int, bytes], ResponseDecoder]


@dataclass(slots=True, eq=False)
class Window:
    """One slave's open window."""

    until: float = 0.0
    signatures: set[bytes] = field(default_factory=set)  # answers that may still come
    owner: LineRequest | None = None
    decoder: ResponseDecoder | None = None  # recognises the lost answer itself
    pending: int = 0  # the owner's attempts whose answers may still come
    sent_at: float | None = None  # when the owner's latest lost attempt was sent


class LateWindows:
    """The open windows, by slave."""

    def __init__(self, new_decoder: NewDecoder) -> None:
        self.windows: dict[int, Window] = {}
        self.new_decoder = new_decoder

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

    def holds(self, request: LineRequest, now: float) -> bool:
        """True when ``request`` could be confused with a lost answer still on its way."""
        window = self.windows.get(request.slave)
        return (
            window is not None
            and now < window.until
            and answer_signature(request.pdu) in window.signatures
            and request is not window.owner
        )

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
