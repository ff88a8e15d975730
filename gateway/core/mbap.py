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

from typing import NamedTuple

from .errors import FramingError

HEADER_LENGTH = 7
MIN_LENGTH_FIELD = 2  # unit id + function code
MAX_LENGTH_FIELD = 254  # unit id + 253-byte PDU
MAX_ADU = HEADER_LENGTH - 1 + MAX_LENGTH_FIELD  # 260


class MbapFrame(NamedTuple):
    """One Modbus TCP request or response: transaction id, unit id and PDU."""

    transaction_id: int
    unit_id: int
    pdu: bytes


def encode_mbap(transaction_id: int, unit_id: int, pdu: bytes) -> bytes:
    """Build an ADU: MBAP header (protocol id 0) followed by ``pdu``."""
    length = len(pdu) + 1
    return (
        bytes(
            (
                (transaction_id >> 8) & 0xFF,
                transaction_id & 0xFF,
                0,
                0,
                length >> 8,
                length & 0xFF,
                unit_id & 0xFF,
            )
        )
        + pdu
    )


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
        frame = MbapFrame((buffer[0] << 8) | buffer[1], buffer[6], bytes(buffer[HEADER_LENGTH:end]))
        del buffer[:end]
        return frame
