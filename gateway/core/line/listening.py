"""Listening: what the machine does with frames it hears but did not ask for.

A layer of ``LineCore``'s class body (see ``ends.py`` for the layering), between the
end of an attempt and sending: the wire hands it the bytes no attempt took (all bytes
while nothing of ours is on the wire, the bytes an attempt's decoder refused while one
is); the ``foreign`` part frames and classifies them, and this layer notes foreign
master frames and learns slaves' timing from the foreign requests' answers. It is
also where a redundancy pair reads the bus: ``last_master_frame_at``,
``last_frame_at``, ``heard_master_frames`` and ``set_listening``.
"""

from __future__ import annotations

from ..outcome import LineEvent
from .ends import AttemptEnds
from .foreign import ForeignRequest, HeardKind, Own
from .records import Note


class Listening(AttemptEnds):
    """Frames heard besides our answers (see the module doc)."""

    char_time: float

    def hear(self, data: bytes, now: float, stop: bool = False) -> bool:
        """Bytes heard at ``now`` that no attempt took: note foreign master frames, learn
        from their answers; ``True`` when a master frame was among them (with ``stop``,
        the bytes after it are left to ``foreign.take_unframed``)."""
        if self.framing.transaction_ids is not None:
            return False  # a tcp or tls line: its answers name their requests
        own: Own = [(request.slave, request.pdu) for request in self.wire.requests()]
        if self.late.windows:
            own.extend(
                (slave, window.owner.pdu)
                for slave, window in self.late.windows.items()
                if window.owner is not None
            )
        foreign = self.foreign
        master = False
        for heard in foreign.feed(data, now, self.char_time, own, stop):
            if heard.kind is HeardKind.MASTER:
                master = True
                if not foreign.listening:
                    self.notes.append(
                        Note(LineEvent.FOREIGN_MASTER, heard.slave, f"function {heard.pdu[0]}")
                    )
            elif heard.kind is HeardKind.ANSWER and heard.request is not None:
                self._learn_from(heard.request, heard.at)
        return master

    def _learn_from(self, request: ForeignRequest, answered_at: float) -> None:
        """A foreign request's answer came: its slave's turnaround, measured as the line
        measures its own (the answer's end less its transmission time and the request's
        end), teaches the learned timing, so a standby starts with it."""
        timing = self.timing
        slave = request.slave
        if not timing.learn or slave in timing.fixed:
            return
        turnaround = answered_at - request.heard_at - timing.answer_time(request.pdu)
        timing.answered(slave, request.pdu[0], max(0.0, turnaround))

    # -- what a redundancy pair reads of the bus ---------------------------------------------

    @property
    def shared(self) -> bool:
        """True while a foreign master frame was heard within ``foreign.SHARED_FOR_S``."""
        return self.foreign.shared

    @property
    def last_master_frame_at(self) -> float | None:
        """The end of the last master frame heard that this gateway did not send."""
        return self.foreign.last_master_frame_at

    @property
    def last_frame_at(self) -> float | None:
        """The end of the last intact frame heard: an answer to our attempts or any other."""
        heard, answered = self.foreign.last_frame_at, self.answered_at
        if heard is None or answered is None:
            return answered if heard is None else heard
        return max(heard, answered)

    @property
    def heard_master_frames(self) -> int:
        """Master frames heard while listening (the active peer's)."""
        return self.foreign.heard_master_frames

    @property
    def foreign_frames(self) -> int:
        """Foreign master frames heard while not listening."""
        return self.foreign.foreign_frames

    @property
    def listening(self) -> bool:
        return self.foreign.listening

    def set_listening(self, listening: bool) -> None:
        """A standby listens: master frames heard are its peer's (timed, learned from,
        counted in ``heard_master_frames``), not a foreign master's."""
        self.foreign.listening = listening
