"""RTU requests over a TCP byte stream (an ``rtu-over-tcp`` listener): framing without silence.

Theory of operation: a master that speaks RTU over TCP sends bare RTU frames
(unit, PDU, CRC) with no header, so ``RtuStreamDecoder`` splits the stream by
each request's predicted length (``rtu.request_length``) and checks its CRC;
segment boundaries mean nothing. Only a request whose length cannot be
predicted (a user-defined function code) ends on silence: the driver calls
``silence()`` after its quiet time and the buffered bytes are then one frame.
A bad CRC, or more than one RTU frame's worth of bytes without an end, is a
``FramingError``: the stream cannot be resynchronised with certainty, so the
connection is closed, as for a broken MBAP header. RTU carries no transaction
id: frames are numbered here, for the trace, and answered in order.
"""

from __future__ import annotations

from typing import Final, NoReturn

from . import pdu as fc
from .crc import append_crc, check_crc
from .errors import FramingError
from .mbap import MbapFrame
from .rtu import MAX_RTU_FRAME, NEED_MORE, request_length

#: The shortest RTU request: unit, function, CRC.
MIN_REQUEST: Final = 4
#: Diagnostics requests carry a subfunction and one 16-bit data field (Serial Line 6.8).
_DIAGNOSTICS_LENGTH: Final = 8


def encode_rtu_reply(unit: int, pdu: bytes) -> bytes:
    """An RTU frame for a reply: unit, PDU, CRC (low byte first)."""
    return append_crc(bytes((unit & 0xFF,)) + pdu)


def stream_request_length(prefix: bytes | bytearray) -> int | None:
    """Predicted length of the request starting ``prefix``; ``None`` when only silence can tell."""
    if len(prefix) >= 2 and prefix[1] == fc.DIAGNOSTICS:
        return _DIAGNOSTICS_LENGTH
    return request_length(prefix)


def heard_request(frame: bytes) -> tuple[int, bytes] | str | None:
    """A frame heard between two silences on a line the gateway serves as a slave.

    Returns ``(unit, pdu)`` for a request to act on, a reason (for the log) when the frame
    is damaged, and ``None`` for an intact frame of another shape: another slave's answer on
    the shared bus, to be ignored quietly.
    """
    if len(frame) < MIN_REQUEST or not check_crc(frame):
        return "a frame with a bad CRC, or too short"
    length = stream_request_length(frame)
    if length is not None and length not in (NEED_MORE, len(frame)):
        return None
    return frame[0], frame[1:-2]


class RtuStreamDecoder:
    """Incremental RTU request decoder for a byte stream; same interface as ``MbapDecoder``."""

    __slots__ = ("_buffer", "_failed", "_next_id", "_silent")

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._failed: FramingError | None = None
        self._next_id = 0
        self._silent = False

    @property
    def buffered(self) -> int:
        """Bytes received but not yet handed out as frames."""
        return len(self._buffer)

    @property
    def awaiting_silence(self) -> bool:
        """True when the buffered request can only end on silence (unknown length)."""
        buffer = self._buffer
        return self._failed is None and len(buffer) >= 2 and stream_request_length(buffer) is None

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Append bytes from the stream; refused once the stream failed."""
        if self._failed is not None:
            raise self._failed
        self._buffer += data
        self._silent = False

    def silence(self) -> None:
        """The stream has been quiet for the silence time: a request of unknown length ends."""
        self._silent = True

    def next_frame(self) -> MbapFrame | None:
        """The next complete request (numbered), ``None`` when more bytes are needed.

        Raises ``FramingError`` for a bad CRC or an endless request.
        """
        if self._failed is not None:
            raise self._failed
        buffer = self._buffer
        if len(buffer) < 2:
            return None
        length = stream_request_length(buffer)
        if length is None:
            if len(buffer) > MAX_RTU_FRAME:
                return self._fail("too_long", f"no end after {len(buffer)} bytes")
            if not self._silent:
                return None
            length = len(buffer)
            if length < MIN_REQUEST:
                return self._fail("bad_crc", f"{length}-byte frame is too short for a request")
        elif length == NEED_MORE or len(buffer) < length:
            return None
        if length > MAX_RTU_FRAME:
            return self._fail("too_long", f"a {length}-byte request is longer than an RTU frame")
        frame = bytes(buffer[:length])
        if not check_crc(frame):
            return self._fail("bad_crc", f"CRC of a {length}-byte request does not match")
        del buffer[:length]  # the silence, if any, also follows whatever is left
        number = self._next_id
        self._next_id = (number + 1) & 0xFFFF
        return MbapFrame(number, frame[0], frame[1:-2])

    def _fail(self, kind: str, reason: str) -> NoReturn:
        self._failed = FramingError(kind, reason)
        raise self._failed
