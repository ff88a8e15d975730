"""Foreign masters: request frames on a shared line that this gateway did not send.

Theory of operation. RS-485 has no arbitration: a second master on the bus (another
gateway, a forgotten PLC, an engineer's laptop) talks over this one, and its slaves'
answers look exactly like answers to this gateway's requests. A line of a shared-medium
kind (``rtu``, ``ascii``, ``rtu-over-tcp``: answers named by their shape, not by a
transaction id) therefore frames what it hears besides the answers it waits for:

* while nothing of ours is on the wire, every byte (our own echo removed);
* while our attempt is on the wire, the bytes its answer decoder refused (an intact
  answer goes to the attempt as before, without passing here: the usual answer costs
  nothing more).

An intact frame (valid CRC or LRC) is classified, first match wins:

1. the answer to one of *our* requests (the attempt on the wire, or a lost attempt
   whose late-answer window is open): ours. An exact echo of our own outstanding
   FC 5 or 6 request is our answer, not a foreign master; so is an exact copy of a
   write of ours whose answer is the request itself (FC 5, 6, 21, 22) sent within
   ``OWN_ECHO_FOR_S``, after its late-answer window closed: a very slow slave's
   answer, not another master (one that sends the very same write is heard at its
   next other frame);
2. the answer to a *pending* foreign request of that slave (its length): that
   request is answered; its turnaround (answer start minus request end, as the line
   measures its own) is learned;
3. a request (a function code whose request length the frame has): a *foreign master
   frame*. Except when it comes from the slave our attempt on the wire asks, within that
   attempt: then it may as well be that slave's malformed answer (some slaves answer an FC
   6 write with the value they stored, not the exact echo). It is awaited as a foreign
   request all the same (every protection below stays: our attempt fails as one without
   its answer, 0x0B or a retry where safe), but it marks the line neither shared nor
   heard from another master, so an active gateway of a pair does not step down for it.
   The price: a second master addressing that very slave during that very attempt is not
   counted for that frame; A foreign request awaits its answer until an answer with its signature is
   heard or the line's longest timeout (``max_timeout``) passed;
4. anything else: a frame, nothing more.

While a foreign request awaits its answer, no request of ours whose answer would look
the same (same slave, answer signature: ``records.answer_signature``) is sent
(``holds``), and an answer that looks the same is not taken for ours (``claims``): it
may be either. That refused answer does not end the foreign request's wait (it may have
been ours): the next answer of that shape does, whoever it was for, or its expiry.

The line is *shared* while a foreign master frame was heard within ``SHARED_FOR_S``.
While *listening* (a standby gateway that never transmits), foreign master frames are
the active peer's: they are timed and learned from, never counted as foreign.

RTU frames have no delimiter but silence: bytes are cut at the front into frames
whose length the function code (and byte count) gives and whose CRC checks; a byte
that starts no frame is skipped. Bytes after a gap longer than ``SPLIT_AFTER_S`` (or
the line's silence, if longer) start afresh: what waited before it is searched once
more, as a whole, then dropped. Functions whose request length cannot be told from
the frame (FC 8, user codes) are not recognised as requests.

This part keeps its state and answers questions; the machine notes and learns.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Final

from .. import pdu as fc
from ..ascii import MAX_ASCII_FRAME, decode_ascii
from ..crc import crc16
from ..errors import ResponseError
from ..rtu import (
    BYTE_COUNT_RESPONSES,
    MAX_RTU_FRAME,
    MIN_RTU_FRAME,
    NEED_MORE,
    request_length,
    response_length,
)
from .records import INFINITY, HeardBus, answer_signature
from .response_timing import answer_pdu_length

#: A line is *shared* while a foreign master frame was heard this recently.
SHARED_FOR_S: Final = 10.0
#: RTU bytes after at least this much silence (or the line's silence, if longer) begin a
#: new frame: scheduling delays between two reads of one frame stay below it.
SPLIT_AFTER_S: Final = 0.02
#: Requests kept awaiting their answers per slave (a bound: a master polls one at a time).
PENDING_PER_SLAVE: Final = 8
#: Writes whose normal answer is the request itself, byte for byte.
ANSWERED_BY_ECHO: Final = fc.ECHOED_WRITES - {fc.WRITE_MULTIPLE_COILS, fc.WRITE_MULTIPLE_REGISTERS}
#: How long a copy of one of those writes of ours is taken for its slave's answer.
OWN_ECHO_FOR_S: Final = SHARED_FOR_S
#: Those writes remembered (a bound: the oldest is forgotten first).
OWN_ECHOES_KEPT: Final = 32


class HeardKind(Enum):
    """What an intact frame heard on the line was."""

    OURS = "ours"  # an answer to one of this gateway's requests
    ANSWER = "answer"  # the answer to a pending foreign request
    MASTER = "master"  # a request this gateway did not send
    #: Shaped like a request, from the slave our attempt asks: its malformed answer, or
    #: another master's request to it. Awaited as a foreign request, counted as neither.
    ASKED = "asked"
    FRAME = "frame"  # an intact frame, none of the above


@dataclass(slots=True, eq=False)
class ForeignRequest:
    """A foreign master's request heard on the line, awaiting its answer."""

    slave: int
    pdu: bytes
    heard_at: float  # the end of its frame
    until: float  # no answer is taken for it after this
    claimed: bool = False  # an answer that may be its was refused to one of ours


@dataclass(slots=True, eq=False)
class Heard:
    """One intact frame heard, classified; ``request`` is the foreign one it concerns."""

    kind: HeardKind
    slave: int
    pdu: bytes
    at: float
    request: ForeignRequest | None = None


#: Requests whose answers are this gateway's: (slave, request PDU).
Own = list[tuple[int, bytes]]


def _answer_length(request: bytes, buffer: bytearray) -> int | None:
    """The length of ``request``'s normal answer when the buffer starts like one and the
    request says how long it is (a read's quantity, a write's echo): not the byte count
    the buffer claims. A request frame whose first bytes happen to pass as an answer with
    another byte count (and a matching CRC) is then a request, not that answer."""
    if len(buffer) >= 2 and buffer[1] == request[0]:
        expected = answer_pdu_length(request)
        if expected is not None:
            if request[0] in fc.ECHOED_WRITES:
                return 3 + expected  # unit, PDU, CRC
            if len(buffer) < 3:
                return NEED_MORE
            # A read's answer says its byte count: another count is not this answer.
            return 3 + expected if buffer[2] == expected - 2 else None
    return response_length(request, buffer)


class ForeignMasters:
    """What the line heard that it did not send (see the module doc)."""

    def __init__(self, ascii: bool) -> None:
        self.ascii = ascii
        self.buffer = bytearray()
        self.last_at = -INFINITY  # when the last byte framed here arrived
        self.split_after = SPLIT_AFTER_S
        self.keep_for = 3.0  # how long a foreign request awaits its answer (``max_timeout``)
        #: slave -> its foreign requests awaiting an answer, oldest first.
        self.pending: dict[int, list[ForeignRequest]] = {}
        self.listening = False
        self.shared = False
        self.shared_until = -INFINITY
        #: The end of the last foreign master frame heard (listening or not), ``None``: never.
        self.last_master_frame_at: float | None = None
        #: The end of the last intact frame heard here (``None``: never).
        self.last_frame_at: float | None = None
        self.foreign_frames = 0  # foreign master frames heard while not listening
        self.heard_master_frames = 0  # master frames heard while listening (the peer's)
        #: Our writes answered by their echo (``ANSWERED_BY_ECHO``): frame -> until when a
        #: copy heard is taken for their answer.
        self.own_echoes: dict[bytes, float] = {}

    def configure(self, silence: float, keep_for: float) -> None:
        """The line's silence, and how long a foreign request awaits its answer."""
        self.split_after = max(SPLIT_AFTER_S, silence)
        self.keep_for = keep_for

    def sent_echoed(self, slave: int, pdu: bytes, now: float) -> None:
        """We sent ``pdu`` (in ``ANSWERED_BY_ECHO``) to ``slave``: a copy heard within
        ``OWN_ECHO_FOR_S`` is its answer, however late."""
        frame = bytes((slave,)) + pdu
        echoes = self.own_echoes
        if echoes.pop(frame, None) is None and len(echoes) >= OWN_ECHOES_KEPT:
            del echoes[next(iter(echoes))]
        echoes[frame] = now + OWN_ECHO_FOR_S

    # -- framing ---------------------------------------------------------------------------

    def feed(
        self,
        data: bytes,
        now: float,
        char_time: float,
        own: Own,
        stop: bool = False,
        asked: int = -1,
    ) -> list[Heard]:
        """Bytes heard at ``now``: the intact frames they complete, classified. With
        ``stop``, framing stops after a master frame: what follows it stays unframed (our
        attempt's decoder takes it: ``take_unframed``). ``asked``: the slave our attempt on
        the wire asks; a frame from it is its (malformed) answer, never a master's."""
        buffer = self.buffer
        heard: list[Heard] = []
        if not self.ascii:
            started = now - len(data) * char_time
            if buffer and started - self.last_at > self.split_after:
                self._cut(heard, self.last_at, own, False, asked, final=True)
                buffer.clear()  # what waited for more before the gap: no frame ends there
        buffer += data
        self.last_at = now
        self._cut(heard, now, own, stop, asked)
        del buffer[: max(0, len(buffer) - 2 * MAX_RTU_FRAME)]
        return heard

    def take_unframed(self) -> bytes:
        """The bytes heard after the last frame found (now the caller's, not kept here)."""
        rest = bytes(self.buffer)
        self.buffer.clear()
        return rest

    def _cut(
        self,
        heard: list[Heard],
        at: float,
        own: Own,
        stop: bool,
        asked: int = -1,
        final: bool = False,
    ) -> None:
        """Cut intact frames from the buffer's front into ``heard``, classified."""
        while True:
            frame = self._next_ascii() if self.ascii else self._next_rtu(own, final)
            if frame is None:
                return
            found = self._classify(frame[0], frame[1:], at, own, asked)
            heard.append(found)
            if stop and (found.kind is HeardKind.MASTER or found.kind is HeardKind.ASKED):
                return

    def _next_rtu(self, own: Own, final: bool) -> bytes | None:
        """The next intact frame's unit and PDU (a byte that starts none is skipped);
        ``final``: no more bytes will come for it (a gap followed)."""
        buffer = self.buffer
        while len(buffer) >= MIN_RTU_FRAME:
            length = self._rtu_length(buffer, own, final)
            if length == NEED_MORE:
                return None
            if length == 0:
                del buffer[0]
                continue
            frame = bytes(buffer[: length - 2])
            del buffer[:length]
            return frame
        return None

    def _rtu_length(self, buffer: bytearray, own: Own, final: bool) -> int:
        """The length of the intact frame at the buffer's front, ``NEED_MORE`` while one
        may still be completing, 0 when none starts there."""
        unit = buffer[0]
        candidates: list[int | None] = [
            _answer_length(pdu, buffer) for slave, pdu in own if slave == unit
        ]
        candidates.extend(_answer_length(r.pdu, buffer) for r in self.pending.get(unit, ()))
        candidates.append(request_length(buffer))
        candidates.append(response_length(bytes(buffer[1:2]), buffer))
        waiting = False
        for length in candidates:
            if length is None:
                continue
            if length == NEED_MORE or length > len(buffer):
                waiting = waiting or length <= MAX_RTU_FRAME
            elif (
                length >= MIN_RTU_FRAME
                and not crc16(bytes(buffer[:length]))
                and not _empty_count(buffer, length)
            ):
                return length
        return NEED_MORE if waiting and not final and len(buffer) < MAX_RTU_FRAME else 0

    def _next_ascii(self) -> bytes | None:
        """The next whole ':' ... CR LF frame's unit and PDU (its LRC checked, removed)."""
        buffer = self.buffer
        while True:
            start = buffer.find(b":")
            if start < 0:
                buffer.clear()
                return None
            del buffer[:start]
            end = buffer.find(b"\n")
            restart = buffer.find(b":", 1)
            if restart >= 0 and (end < 0 or restart < end):
                del buffer[:restart]  # a ':' inside a frame: a new frame began
                continue
            if end < 0:
                del buffer[: max(0, len(buffer) - MAX_ASCII_FRAME)]
                return None
            frame = bytes(buffer[: end + 1])
            del buffer[: end + 1]
            try:
                unit, pdu = decode_ascii(frame)
            except ResponseError:
                continue  # damaged: not a frame anybody can act on
            return bytes((unit,)) + pdu

    # -- what a frame is ------------------------------------------------------------------

    def _classify(self, slave: int, pdu: bytes, at: float, own: Own, asked: int = -1) -> Heard:
        self.last_frame_at = at
        frame = bytes((slave,)) + pdu
        length = len(frame) + 2  # as an RTU frame (ASCII's LRC is one byte, RTU's CRC two)
        for owner, request in own:
            if (
                owner == slave
                and response_length(request, frame) == length
                and _may_answer(request, pdu)
            ):
                self._settle(slave, request)
                return Heard(HeardKind.OURS, slave, pdu, at)
        waiting = self.pending.get(slave)
        if waiting:
            for foreign in waiting:
                if (
                    at < foreign.until
                    and response_length(foreign.pdu, frame) == length
                    and _may_answer(foreign.pdu, pdu)
                ):
                    self._answered(foreign)
                    return Heard(HeardKind.ANSWER, slave, pdu, at, foreign)
        if pdu and request_length(frame) == length:
            until = self.own_echoes.get(frame)
            if until is not None and at < until:
                return Heard(HeardKind.OURS, slave, pdu, at)  # a very late answer of ours
            return self._master_frame(slave, pdu, at, counted=slave != asked)
        return Heard(HeardKind.FRAME, slave, pdu, at)

    def _master_frame(self, slave: int, pdu: bytes, at: float, counted: bool = True) -> Heard:
        """A request this gateway did not send: it awaits its answer (not a broadcast).
        Not ``counted``: from the slave our attempt asks, it may be that slave's malformed
        answer as well; awaited all the same, but it marks nothing shared."""
        request = ForeignRequest(slave, pdu, at, at + self.keep_for)
        if not counted:
            if slave:
                self._await(slave, request, at)
            return Heard(HeardKind.ASKED, slave, pdu, at, request)
        self.last_master_frame_at = at
        if slave:
            self._await(slave, request, at)
        if self.listening:
            self.heard_master_frames += 1
        else:
            self.foreign_frames += 1
            self.shared = True
            self.shared_until = at + SHARED_FOR_S
        return Heard(HeardKind.MASTER, slave, pdu, at, request)

    def _await(self, slave: int, request: ForeignRequest, at: float) -> None:
        waiting = self.pending.setdefault(slave, [])
        waiting[:] = [r for r in waiting if at < r.until][-(PENDING_PER_SLAVE - 1) :]
        waiting.append(request)

    def _settle(self, slave: int, request: bytes) -> None:
        """An answer to our ``request`` came after one that looked the same was refused to
        it: the two answers awaited (ours, the foreign request's) have both come."""
        for foreign in list(self.pending.get(slave, ())):
            if foreign.claimed and answer_signature(foreign.pdu) == answer_signature(request):
                self._answered(foreign)

    def _answered(self, request: ForeignRequest) -> None:
        waiting = self.pending[request.slave]
        waiting.remove(request)
        if not waiting:
            del self.pending[request.slave]

    # -- questions --------------------------------------------------------------------------

    def claims(self, slave: int, request: bytes, answer: bytes, now: float) -> bool:
        """True when ``answer``, taken for our ``request`` to ``slave``, may be a pending
        foreign request's answer (same slave, same function and answer signature): ours
        must not take it. The foreign request keeps waiting: the answer may have been ours,
        and then the foreign one is still to come (it ends the wait when heard while
        nothing of ours that looks the same is on the wire, or at its expiry)."""
        foreign = self._alike(slave, request, now, bool(answer[0] & fc.EXCEPTION_FLAG))
        if foreign is None:
            return False
        if foreign.claimed:
            self._answered(foreign)  # a second look-alike: its answer has come by now
        foreign.claimed = True
        return True

    def holds(self, slave: int, request: bytes, now: float) -> bool:
        """True when ``request`` to ``slave`` must wait: a pending foreign request's answer
        would look the same as its answer."""
        return self._alike(slave, request, now) is not None

    def _alike(
        self, slave: int, request: bytes, now: float, exception: bool = False
    ) -> ForeignRequest | None:
        """The pending foreign request whose answer looks like ours (the same signature, or
        with ``exception`` the same function). An identical write is not one: the same write,
        the same answer."""
        waiting = self.pending.get(slave)
        if not waiting:
            return None
        signature = answer_signature(request)
        for foreign in list(waiting):
            if now >= foreign.until:
                self._answered(foreign)
                continue
            if foreign.pdu == request and request[0] in fc.ECHOED_WRITES:
                continue
            if exception:
                if foreign.pdu[0] == request[0]:
                    return foreign
            elif answer_signature(foreign.pdu) == signature:
                return foreign
        return None

    def expire(self, now: float) -> None:
        """Give up the foreign requests whose answers did not come in time."""
        for slave, waiting in list(self.pending.items()):
            waiting[:] = [request for request in waiting if now < request.until]
            if not waiting:
                del self.pending[slave]

    def earliest(self) -> float:
        """When the first pending foreign request expires."""
        return min(
            (r.until for waiting in self.pending.values() for r in waiting), default=INFINITY
        )

    def handover(self) -> HeardBus:
        pending = tuple(
            (r.slave, r.pdu, r.heard_at, r.until)
            for waiting in self.pending.values()
            for r in waiting
        )
        return HeardBus(
            self.last_master_frame_at, self.last_frame_at,
            self.shared_until if self.shared else -INFINITY,
            self.foreign_frames, self.heard_master_frames, self.listening, pending,
            tuple(self.own_echoes.items()),
        )  # fmt: skip

    def take_over(self, heard: HeardBus, now: float) -> None:
        """Go on from what the line this one replaces heard (a reload that reopens it)."""
        self.last_master_frame_at = heard.last_master_frame_at
        self.last_frame_at = heard.last_frame_at
        self.foreign_frames = heard.foreign_frames
        self.heard_master_frames = heard.heard_master_frames
        self.listening = heard.listening
        self.shared = now < heard.shared_until
        self.shared_until = heard.shared_until
        for slave, pdu, heard_at, until in heard.pending:
            if now < until:
                request = ForeignRequest(slave, pdu, heard_at, until)
                self.pending.setdefault(slave, []).append(request)
        for frame, until in heard.own_echoes:
            if now < until:
                self.own_echoes[frame] = until

    def decays(self, now: float) -> bool:
        """True when the line stops being shared now (no foreign master frame for a while)."""
        if self.shared and now >= self.shared_until:
            self.shared = False
            return True
        return False


def _empty_count(buffer: bytearray, length: int) -> bool:
    """True when the ``length`` bytes at the front would be an answer whose byte count is
    0: no function answers so (a read asks for 1 item at least), and a CRC that checks
    there by chance (1 in 65,536) would hide the request those bytes begin."""
    return length == 5 and buffer[1] in BYTE_COUNT_RESPONSES and buffer[2] == 0


def _may_answer(request: bytes, answer: bytes) -> bool:
    """True when ``answer`` may answer ``request``: its function's exception, or its
    function with the length the request implies (a read's byte count) and, for the writes
    that echo, the echo itself."""
    if answer[0] & 0x7F != request[0]:
        return False
    if answer[0] & fc.EXCEPTION_FLAG:
        return True
    if request[0] in fc.ECHOED_WRITES:
        return answer == fc.write_response(request)
    expected = answer_pdu_length(request)
    return expected is None or len(answer) == expected
