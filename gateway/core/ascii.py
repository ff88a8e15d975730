"""Modbus ASCII framing (Modbus over Serial Line v1.02, 2.5.2): encoding and response decoding.

Theory of operation: an ASCII frame is ':' then unit, PDU and LRC as two upper-case
hexadecimal characters per byte, then CR LF; at most 513 characters. The LRC is the
two's complement of the 8-bit sum of unit and PDU. A frame ends at its LF, never on
silence, so the line needs no t3.5: only the inter-character timeout (1 s by default)
abandons a frame whose characters stopped coming. Characters outside a frame are
ignored, as the specification says; a ':' inside a frame abandons it and starts a
new one (``ResponseError`` of kind ``restarted``, the new frame kept in ``leftover``).
``AsciiResponseDecoder`` has the interface of ``RtuResponseDecoder`` and applies the
same checks: unit, function, byte count or echo of the request on the wire.
"""

from __future__ import annotations

import binascii
from typing import Final

from .errors import ResponseError
from .rtu import RtuFrame, check_identity, response_length

#: The longest frame: ':' + 2 x 255 characters + CR LF (2.5.2.1).
MAX_ASCII_FRAME: Final = 513
#: Characters after the ':' a frame may have, CR LF included.
_MAX_BODY: Final = MAX_ASCII_FRAME - 1
_START: Final = b":"
_LF: Final = b"\n"


def lrc(data: bytes | bytearray) -> int:
    """Longitudinal redundancy check: two's complement of the 8-bit sum."""
    return -sum(data) & 0xFF


def encode_ascii(unit: int, pdu: bytes) -> bytes:
    """Build the ASCII ADU: ':', unit, PDU and LRC in upper-case hex, CR LF."""
    body = bytes((unit,)) + pdu
    body += bytes((lrc(body),))
    return b":" + binascii.hexlify(body).upper() + b"\r\n"


def decode_ascii(frame: bytes) -> RtuFrame:
    """Check one whole ASCII frame (':' to LF) and return its unit and PDU.

    For slaves and simulators; raises ``ResponseError`` (``short_frame``, ``bad_char``,
    ``crc`` for a wrong LRC, ``oversize``).
    """
    if len(frame) > MAX_ASCII_FRAME:
        raise ResponseError("oversize", f"ASCII frame of {len(frame)} characters")
    if not frame.startswith(_START) or not frame.endswith(b"\r\n"):
        raise ResponseError("bad_char", "ASCII frame without ':' start or CR LF end")
    raw = _unhex(frame[1:-2])
    return RtuFrame(raw[0], raw[1:-1])


def _unhex(text: bytes | bytearray) -> bytes:
    if len(text) < 6:  # unit, function, LRC
        raise ResponseError("short_frame", f"ASCII frame of {len(text) + 3} characters")
    try:
        raw = binascii.unhexlify(text)
    except (binascii.Error, ValueError):
        raise ResponseError("bad_char", "ASCII frame with a non-hexadecimal character") from None
    if lrc(raw[:-1]) != raw[-1]:
        raise ResponseError("crc", "response LRC mismatch")
    return raw


class AsciiResponseDecoder:
    """Collects the characters of one ASCII response and checks it against the request."""

    __slots__ = (
        "_buffer",
        "_function",
        "_in_frame",
        "_looks",
        "_request_pdu",
        "_unit",
        "leftover",
    )

    def __init__(self, unit: int, request_pdu: bytes) -> None:
        self._unit = unit
        self._request_pdu = request_pdu
        self._function = request_pdu[0]
        self._buffer = bytearray()  # the characters after ':'
        self._in_frame = False
        self._looks = False
        self.leftover = b""

    @property
    def buffered(self) -> int:
        """Characters of the response collected so far (its ':' included)."""
        return len(self._buffer) + 1 if self._in_frame else 0

    @property
    def waits_for_silence(self) -> bool:
        """True inside a frame: the inter-character timeout abandons it."""
        return self._in_frame

    @property
    def looks_like_answer(self) -> bool:
        """True when the frame had the awaited unit, function and length: only its LRC was bad."""
        return self._looks

    def feed(self, data: bytes | bytearray | memoryview) -> RtuFrame | None:
        """Add received characters; the checked response once its LF came, else ``None``."""
        chunk = bytes(data)
        if not self._in_frame:
            start = chunk.find(_START)
            if start < 0:
                return None  # outside a frame: ignored
            chunk = chunk[start + 1 :]
            self._in_frame = True
        buffer = self._buffer
        restart = chunk.find(_START)
        end = chunk.find(_LF)
        if restart >= 0 and (end < 0 or restart < end):
            self.leftover = chunk[restart:]
            raise ResponseError("restarted", "':' inside a frame: a new frame began")
        stop = end + 1 if end >= 0 else len(chunk)
        if len(buffer) + stop > _MAX_BODY:
            self.leftover = chunk[stop:]
            self._in_frame = False
            raise ResponseError("oversize", f"response exceeds {MAX_ASCII_FRAME} characters")
        if end < 0:
            buffer += chunk
            return None
        buffer += chunk[:stop]
        self.leftover = chunk[stop:]
        self._in_frame = False
        return self._check()

    def end_of_frame(self) -> RtuFrame:
        """No character came for the inter-character timeout: the frame is abandoned."""
        count = self.buffered
        raise ResponseError("incomplete", f"ASCII frame stopped after {count} characters")

    def reset(self) -> None:
        """Forget a discarded frame and wait for the real answer."""
        self._buffer.clear()
        self._in_frame = False
        self._looks = False
        self.leftover = b""

    def _check(self) -> RtuFrame:
        buffer = self._buffer
        if len(buffer) < 2 or buffer[-2] != 0x0D:
            raise ResponseError("bad_char", "ASCII frame ends in LF without CR")
        text = buffer[:-2]
        if len(text) < 6:  # unit, function, LRC
            raise ResponseError("short_frame", f"ASCII frame of {len(text) + 3} characters")
        try:
            raw = binascii.unhexlify(text)
        except (binascii.Error, ValueError):
            raise ResponseError(
                "bad_char", "ASCII frame with a non-hexadecimal character"
            ) from None
        if lrc(raw[:-1]) != raw[-1]:
            # The RTU frame of the same content is one byte longer (CRC16 for the LRC).
            self._looks = (
                raw[0] == self._unit
                and raw[1] & 0x7F == self._function
                and response_length(self._request_pdu, raw) == len(raw) + 1
            )
            raise ResponseError("crc", "response LRC mismatch")
        check_identity(self._unit, self._function, self._request_pdu, raw[0], raw[1:-1])
        return RtuFrame(raw[0], raw[1:-1])
