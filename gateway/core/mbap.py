"""Modbus TCP framing: the MBAP header (Modbus Messaging on TCP/IP Implementation Guide v1.0b).

Theory of operation: ``MbapDecoder`` is fed whatever the socket delivered and
hands out complete frames, so any chunking of a stream gives the same frames.
It never holds more than one partial ADU (at most 260 bytes) beyond the frames
already complete in its buffer, and it checks the header before it waits for
a body: a protocol id other than 0 or a length outside 2..254 is a
``FramingError``, after which the stream cannot be trusted and the decoder
refuses further input.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from .errors import FramingError, ResponseError
from .rtu import RtuFrame, check_identity

HEADER_LENGTH = 7
MIN_LENGTH_FIELD = 2  # unit id + function code
MAX_LENGTH_FIELD = 254  # unit id + 253-byte PDU
MAX_ADU = HEADER_LENGTH - 1 + MAX_LENGTH_FIELD  # 260


_pack_header = struct.Struct(">HHHB").pack  # transaction id, protocol id, length, unit id
_tuple_new = tuple.__new__  # ``MbapFrame(...)`` without its Python-level ``__new__`` (per request)


class MbapFrame(NamedTuple):
    """One Modbus TCP request or response: transaction id, unit id and PDU."""

    transaction_id: int
    unit_id: int
    pdu: bytes


def encode_mbap(transaction_id: int, unit_id: int, pdu: bytes) -> bytes:
    """Build an ADU: MBAP header (protocol id 0) followed by ``pdu``."""
    return _pack_header(transaction_id & 0xFFFF, 0, len(pdu) + 1, unit_id & 0xFF) + pdu


class MbapDecoder:
    """Incremental MBAP decoder: ``feed`` bytes, then take frames with ``next_frame``."""

    __slots__ = ("_buffer", "_failed")

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._failed: FramingError | None = None

    @property
    def buffered(self) -> int:
        """Bytes received but not yet handed out as frames."""
        return len(self._buffer)

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Append bytes from the stream; refused once the stream failed."""
        if self._failed is not None:
            raise self._failed
        self._buffer += data

    def next_frame(self) -> MbapFrame | None:
        """Return the next complete frame, ``None`` when more bytes are needed.

        Raises ``FramingError`` for a header no Modbus TCP peer sends.
        """
        if self._failed is not None:
            raise self._failed
        buffer = self._buffer
        if len(buffer) < HEADER_LENGTH:
            return None
        protocol_id = (buffer[2] << 8) | buffer[3]
        length = (buffer[4] << 8) | buffer[5]
        if protocol_id != 0:
            self._failed = FramingError(
                "bad_protocol_id", f"MBAP protocol id {protocol_id} is not 0"
            )
            raise self._failed
        if not MIN_LENGTH_FIELD <= length <= MAX_LENGTH_FIELD:
            self._failed = FramingError(
                "bad_length",
                f"MBAP length {length} outside {MIN_LENGTH_FIELD}..{MAX_LENGTH_FIELD}",
            )
            raise self._failed
        end = HEADER_LENGTH - 1 + length
        if len(buffer) < end:
            return None
        frame = _tuple_new(
            MbapFrame, ((buffer[0] << 8) | buffer[1], buffer[6], bytes(buffer[HEADER_LENGTH:end]))
        )
        del buffer[:end]
        return frame


class MbapResponseDecoder:
    """Collects one Modbus TCP answer from a downstream slave and checks it.

    The interface of ``RtuResponseDecoder``, for a line of ``kind = "tcp"``: the gateway
    numbers its own requests, so the answer is the frame with the transaction id on the
    wire (``unexpected_tid`` for any other, skipped like another unit's RTU frame); then
    the function and the byte count or echo, as on RTU. The unit id is not checked: the
    transaction id already names the request, and many TCP devices answer with a unit
    id of their own. A header no Modbus TCP peer sends (``bad_header``) means the stream
    is out of step: the driver should reconnect. No checksum: never ``looks_like_answer``.
    """

    __slots__ = ("_buffer", "_function", "_request_pdu", "_tid", "leftover")

    def __init__(self, transaction_id: int, request_pdu: bytes) -> None:
        self._tid = transaction_id
        self._request_pdu = request_pdu
        self._function = request_pdu[0]
        self._buffer = bytearray()
        self.leftover = b""

    @property
    def buffered(self) -> int:
        """Bytes of the answer collected so far."""
        return len(self._buffer)

    @property
    def waits_for_silence(self) -> bool:
        """Never: every MBAP frame carries its length."""
        return False

    @property
    def looks_like_answer(self) -> bool:
        """Never: without a checksum, a frame is the answer or not an answer at all."""
        return False

    def feed(self, data: bytes | bytearray | memoryview) -> RtuFrame | None:
        """Add received bytes; the checked answer once complete, ``None`` while incomplete.

        The answer comes as (unit id, PDU), as every framing's answers do.
        """
        buffer = self._buffer
        buffer += data
        if len(buffer) < HEADER_LENGTH:
            return None
        protocol_id = (buffer[2] << 8) | buffer[3]
        length = (buffer[4] << 8) | buffer[5]
        if protocol_id != 0 or not MIN_LENGTH_FIELD <= length <= MAX_LENGTH_FIELD:
            buffer.clear()
            raise ResponseError(
                "bad_header", f"MBAP header with protocol id {protocol_id}, length {length}"
            )
        end = HEADER_LENGTH - 1 + length
        if len(buffer) < end:
            return None
        self.leftover = bytes(buffer[end:])
        del buffer[end:]
        tid = (buffer[0] << 8) | buffer[1]
        pdu = bytes(buffer[HEADER_LENGTH:])
        if tid != self._tid:
            raise ResponseError(
                "unexpected_tid", f"answer with transaction id {tid}, expected {self._tid}"
            )
        check_identity(buffer[6], self._function, self._request_pdu, buffer[6], pdu)
        return RtuFrame(buffer[6], pdu)

    def end_of_frame(self) -> RtuFrame:
        """Not used on TCP (``waits_for_silence`` is never true)."""
        raise ResponseError("incomplete", f"MBAP answer stopped after {len(self._buffer)} bytes")

    def reset(self) -> None:
        """Forget a discarded frame and wait for the real answer."""
        self._buffer.clear()
        self.leftover = b""


class TransactionIds:
    """The gateway's own transaction ids on one downstream TCP connection.

    ``encode`` numbers each request (1, 2, ... 65535, 0, 1, ...); ``decoder`` then waits for
    the answer with that number. The line core calls them in that order for every attempt.
    """

    __slots__ = ("current",)

    def __init__(self, start: int = 0) -> None:
        self.current = start & 0xFFFF

    def encode(self, unit: int, pdu: bytes) -> bytes:
        """The next request's ADU, under a new transaction id."""
        self.current = (self.current + 1) & 0xFFFF
        return encode_mbap(self.current, unit, pdu)

    def decoder(self, unit: int, request_pdu: bytes) -> MbapResponseDecoder:
        """The decoder of the answer to the request just encoded."""
        return MbapResponseDecoder(self.current, request_pdu)
