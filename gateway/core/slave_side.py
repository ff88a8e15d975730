"""What a slave hears on a serial line: requests told apart from everything else.

Theory of operation: the ``serial-slave`` listener answers on a serial line as
the slaves the gateway routes. Everything it decides about the bytes it hears
lives here, without I/O or clocks, so it is tested with literal inputs:

* **ASCII framing** (``AsciiRequestReader``): a frame runs from ':' to LF
  (Modbus over Serial Line 2.5.2). Characters outside a frame are ignored; a ':'
  inside one abandons it and starts a new one; more than 513 characters abandon
  it; the driver reports the inter-character timeout (``timed_out``) when the
  characters of a frame stop coming. What is kept is bounded by one frame.
* **Is it a request?** (``heard_ascii_request``, and ``rtu_stream.heard_request``
  for RTU): a frame is served only when its LRC (CRC) is right and its length is
  the one its function code implies for a request; an intact frame of another
  shape is another slave's answer on the shared bus, ignored quietly.
* **Own echo** (``OwnEcho``): a half-duplex adapter that hears itself hands the
  answer just written back as received bytes. Exactly those bytes are dropped;
  anything else is the line's, and the echo is still expected after it (until
  the next answer is written), as on a downstream line with ``echo = true``.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Final

from .ascii import MAX_ASCII_FRAME, decode_ascii
from .echo import strip_echo
from .errors import ResponseError
from .rtu import NEED_MORE
from .rtu_stream import stream_request_length

#: Characters after the ':' a frame may have, CR LF included.
_MAX_BODY: Final = MAX_ASCII_FRAME - 1


class FrameFault(StrEnum):
    """Why a frame heard on the line is not served: the ``kind`` of ``protocol_errors_total``.

    The values are those of the other listeners where the meaning is the same: a wrong LRC
    is ``bad_crc``, as on lines it counts as a CRC error; an endless frame is ``too_long``.
    """

    BAD_CHECK = "bad_crc"  # CRC (LRC) wrong, or a frame too short to be a request
    BAD_CHAR = "bad_char"  # a non-hexadecimal character, or LF without CR
    RESTARTED = "restarted"  # a ':' inside a frame: the frame so far is abandoned
    OVERSIZE = "too_long"  # more than a frame without an end (513 characters, 2 RTU frames)
    INCOMPLETE = "incomplete"  # the characters stopped for the inter-character timeout


#: What each refusal of ``decode_ascii`` means on the slave side.
_FAULT_BY_KIND: Final = {
    "crc": FrameFault.BAD_CHECK,
    "short_frame": FrameFault.BAD_CHECK,
    "bad_char": FrameFault.BAD_CHAR,
    "oversize": FrameFault.OVERSIZE,
}

Heard = tuple[int, bytes] | FrameFault | None
"""``(unit, pdu)`` to act on, a fault (damaged frame), or ``None`` (an intact frame of
another shape: another slave's answer)."""


class AsciiRequestReader:
    """Splits the characters heard on an ASCII line into whole frames (':' to CR LF)."""

    __slots__ = ("_body", "_in_frame")

    def __init__(self) -> None:
        self._body = bytearray()  # the characters after ':', at most ``_MAX_BODY``
        self._in_frame = False

    @property
    def in_frame(self) -> bool:
        """True between a ':' and its LF: the inter-character timeout then runs."""
        return self._in_frame

    @property
    def buffered(self) -> int:
        """Characters of the frame under way (its ':' included)."""
        return len(self._body) + 1 if self._in_frame else 0

    def feed(self, data: bytes | bytearray) -> list[bytes | FrameFault]:
        """Add received characters; whole frames (``b":...\\r\\n"``) and faults, in order."""
        events: list[bytes | FrameFault] = []
        body = self._body
        index, end = 0, len(data)
        while index < end:
            if not self._in_frame:
                start = data.find(b":", index)
                if start < 0:
                    break  # outside a frame: ignored
                self._in_frame = True
                body.clear()
                index = start + 1
                continue
            colon = data.find(b":", index)
            stop = data.find(b"\n", index)
            restart = colon >= 0 and (stop < 0 or colon < stop)
            if restart:
                stop = colon
            after = end if stop < 0 else stop + 1  # where this piece of the frame ends
            size = (colon - index) if restart else (after - index)
            if len(body) + size > _MAX_BODY:
                events.append(FrameFault.OVERSIZE)
                body.clear()
                self._in_frame = False
                index = colon if restart else after  # a ':' begins the next frame
                continue
            if restart:
                events.append(FrameFault.RESTARTED)
                body.clear()  # still in a frame: the new one
                index = colon + 1
                continue
            body += data[index:after]
            index = after
            if stop >= 0:
                events.append(b":" + bytes(body))
                body.clear()
                self._in_frame = False
        return events

    def timed_out(self) -> FrameFault | None:
        """No character came for the inter-character timeout: a frame under way is dropped."""
        if not self._in_frame:
            return None
        self.reset()
        return FrameFault.INCOMPLETE

    def reset(self) -> None:
        """Forget the frame under way (the port was lost)."""
        self._body.clear()
        self._in_frame = False


def heard_ascii_request(frame: bytes) -> Heard:
    """A whole ASCII frame heard on a line the gateway serves as a slave.

    Returns ``(unit, pdu)`` for a request to act on, a ``FrameFault`` for a damaged
    frame, ``None`` for an intact frame of another shape (another slave's answer).
    """
    try:
        unit, pdu = decode_ascii(frame)
    except ResponseError as error:
        return _FAULT_BY_KIND.get(error.kind, FrameFault.BAD_CHAR)
    return request_or_none(unit, pdu)


def request_or_none(unit: int, pdu: bytes) -> tuple[int, bytes] | None:
    """``(unit, pdu)`` when the PDU has a request's length for its function code, else ``None``.

    The length is the RTU one (unit, PDU, two check bytes): the same rule for both framings.
    """
    rtu_length = len(pdu) + 3
    length = stream_request_length(bytes((unit,)) + pdu)
    if length is not None and length not in (NEED_MORE, rtu_length):
        return None
    return unit, pdu


class OwnEcho:
    """The answer just written, expected back from an adapter that echoes; dropped exactly."""

    __slots__ = ("_frame", "_left")

    def __init__(self) -> None:
        self._left = b""
        self._frame = b""

    @property
    def expected(self) -> int:
        """Bytes of the echo still to come back."""
        return len(self._left)

    def sent(self, frame: bytes) -> None:
        """``frame`` went on the wire: its echo replaces any echo still expected."""
        self._left = self._frame = frame

    def strip(self, data: bytes) -> bytes:
        """``data`` without the echo (``echo.strip_echo``); the rest is the line's."""
        if not self._left:
            return data
        data, self._left = strip_echo(data, self._left, self._frame)
        return data
