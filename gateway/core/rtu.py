"""Modbus RTU framing (Modbus over Serial Line v1.02): encoding and response decoding.

Theory of operation: an RTU frame is unit + PDU + CRC16 (low byte first), at
most 256 bytes. ``frame_length`` predicts a frame's total length from its first
bytes, by function code and byte count, so the gateway knows that a response
is complete the moment its last byte arrives, without waiting for line
silence. It returns ``None`` for function codes whose length cannot be known
from the frame; those frames end at t3.5 of silence (``RtuResponseDecoder.end_of_frame``).
``RtuResponseDecoder`` accepts a response only when its CRC is good and it
comes from the unit and for the function that was asked, with the byte count
or echo that the request implies; anything else raises ``ResponseError`` and
is never passed on.
"""

from __future__ import annotations

from typing import Final, NamedTuple, NoReturn

from . import pdu as fc
from .crc import check_crc, crc16
from .errors import ResponseError

MAX_RTU_FRAME: Final = 256
MIN_RTU_FRAME: Final = 4  # unit + function + CRC
MIN_ANSWER: Final = 5  # the shortest answer: an exception (unit, function, code, CRC)
#: Bytes in front of an answer searched for its start: a transceiver turning around puts a
#: byte or two there. Fewer than a request's echo (8 bytes for a read): an adapter that
#: echoes needs ``echo = true``, not this.
MAX_NOISE: Final = 4
NEED_MORE: Final = -1  # the frame's length cannot be told yet: wait for more bytes


_tuple_new: Final = tuple.__new__


class RtuFrame(NamedTuple):
    """A checked RTU frame: the unit (slave address) and the PDU, CRC removed."""

    unit: int
    pdu: bytes


def encode_rtu(unit: int, pdu: bytes) -> bytes:
    """Build the serial ADU: unit, PDU, CRC16 low byte first."""
    body = bytes((unit,)) + pdu
    crc = crc16(body)  # ``crc16_bytes``, inline: once per request frame
    return body + bytes((crc & 0xFF, crc >> 8))


# Responses whose length is fixed whatever the request: total frame length.
_FIXED_RESPONSE_LENGTH: Final = {
    fc.WRITE_SINGLE_COIL: 8,
    fc.WRITE_SINGLE_REGISTER: 8,
    fc.WRITE_MULTIPLE_COILS: 8,
    fc.WRITE_MULTIPLE_REGISTERS: 8,
    fc.READ_EXCEPTION_STATUS: 5,
    fc.GET_COMM_EVENT_COUNTER: 8,
    fc.MASK_WRITE_REGISTER: 10,
}

#: Functions whose answer carries a one-byte byte count at offset 2: total = 3 + count + 2.
BYTE_COUNT_RESPONSES: Final = frozenset(
    {
        fc.READ_COILS,
        fc.READ_DISCRETE_INPUTS,
        fc.READ_HOLDING_REGISTERS,
        fc.READ_INPUT_REGISTERS,
        fc.GET_COMM_EVENT_LOG,
        fc.REPORT_SERVER_ID,
        fc.READ_FILE_RECORD,
        fc.READ_WRITE_MULTIPLE_REGISTERS,
    }
)

# Responses that echo the request: total = 1 + len(request PDU) + 2.
_ECHO_RESPONSES: Final = frozenset({fc.DIAGNOSTICS, fc.WRITE_FILE_RECORD})


def response_length(request_pdu: bytes, prefix: bytes | bytearray) -> int | None:
    """Total length of the response frame that starts with ``prefix``.

    Returns ``NEED_MORE`` while more bytes are needed to tell, and ``None`` when
    the length cannot be known from the frame (end it on line silence).
    """
    if len(prefix) < 2:
        return NEED_MORE
    function = prefix[1]
    if function & fc.EXCEPTION_FLAG:
        return 5
    if function in BYTE_COUNT_RESPONSES:
        return 5 + prefix[2] if len(prefix) >= 3 else NEED_MORE
    fixed = _FIXED_RESPONSE_LENGTH.get(function)
    if fixed is not None:
        return fixed
    if function in _ECHO_RESPONSES:
        if request_pdu and request_pdu[0] == function:
            return 3 + len(request_pdu)
        return None
    if function == fc.READ_FIFO_QUEUE:
        return 6 + ((prefix[2] << 8) | prefix[3]) if len(prefix) >= 4 else NEED_MORE
    if function == fc.ENCAPSULATED_INTERFACE:
        return _device_id_length(prefix)
    return None


def _device_id_length(prefix: bytes | bytearray) -> int | None:
    """Length of a Read Device Identification (43/14) response, walking its object list."""
    if len(prefix) < 3:
        return NEED_MORE
    if prefix[2] != fc.MEI_READ_DEVICE_ID:
        return None
    if len(prefix) < 8:
        return NEED_MORE
    count = prefix[7]
    offset = 8
    for _ in range(count):
        if len(prefix) < offset + 2:
            return NEED_MORE
        offset += 2 + prefix[offset + 1]
        if offset > MAX_RTU_FRAME:
            return MAX_RTU_FRAME + 1
    return offset + 2


def request_length(prefix: bytes | bytearray) -> int | None:
    """Total length of the request frame that starts with ``prefix`` (for slaves and simulators).

    Same conventions as ``response_length``.
    """
    if len(prefix) < 2:
        return NEED_MORE
    function = prefix[1]
    if function in (
        fc.READ_COILS,
        fc.READ_DISCRETE_INPUTS,
        fc.READ_HOLDING_REGISTERS,
        fc.READ_INPUT_REGISTERS,
        fc.WRITE_SINGLE_COIL,
        fc.WRITE_SINGLE_REGISTER,
    ):
        return 8
    if function in (
        fc.READ_EXCEPTION_STATUS,
        fc.GET_COMM_EVENT_COUNTER,
        fc.GET_COMM_EVENT_LOG,
        fc.REPORT_SERVER_ID,
    ):
        return 4
    if function in (fc.WRITE_MULTIPLE_COILS, fc.WRITE_MULTIPLE_REGISTERS):
        return 9 + prefix[6] if len(prefix) >= 7 else NEED_MORE
    if function in (fc.READ_FILE_RECORD, fc.WRITE_FILE_RECORD):
        return 5 + prefix[2] if len(prefix) >= 3 else NEED_MORE
    if function == fc.MASK_WRITE_REGISTER:
        return 10
    if function == fc.READ_WRITE_MULTIPLE_REGISTERS:
        return 13 + prefix[10] if len(prefix) >= 11 else NEED_MORE
    if function == fc.READ_FIFO_QUEUE:
        return 6
    if function == fc.ENCAPSULATED_INTERFACE:
        if len(prefix) < 3:
            return NEED_MORE
        return 7 if prefix[2] == fc.MEI_READ_DEVICE_ID else None
    if function == fc.DIAGNOSTICS:
        return None
    return None


class RtuResponseDecoder:
    """Collects the bytes of one response and checks it against the request on the wire."""

    __slots__ = ("_buffer", "_expected", "_function", "_request_pdu", "_unit", "leftover")

    def __init__(self, unit: int, request_pdu: bytes) -> None:
        self._unit = unit
        self._request_pdu = request_pdu
        self._function = request_pdu[0]
        self._buffer = bytearray()
        self._expected: int | None = NEED_MORE
        self.leftover = b""

    @property
    def buffered(self) -> int:
        """Bytes of the response collected so far."""
        return len(self._buffer)

    @property
    def waits_for_silence(self) -> bool:
        """True when the frame's end can only be found by t3.5 of line silence."""
        return self._expected is None

    def feed(self, data: bytes | bytearray | memoryview) -> RtuFrame | None:
        """Add received bytes; return the response once complete, ``None`` while incomplete.

        Bytes past the end of the frame are not part of it: they are left in
        ``leftover`` for the caller (the next frame on the line, or noise).
        Raises ``ResponseError`` for a frame that must not be passed on.
        """
        buffer = self._buffer
        before = len(buffer)
        room = MAX_RTU_FRAME - before
        rest = data[room:]
        buffer += data[:room]  # bounded before buffering: never more than one RTU frame
        if self._expected == NEED_MORE:
            self._expected = response_length(self._request_pdu, buffer)
            if self._expected is not None and self._expected > MAX_RTU_FRAME:
                self._skip_noise(bytes(buffer) + bytes(rest), whole_only=self._starts_like_answer)
                raise ResponseError("oversize", f"response announces {self._expected} bytes")
        expected = self._expected
        if expected is None or expected == NEED_MORE or len(buffer) < expected:
            if rest:
                self._skip_noise(bytes(buffer) + bytes(rest), whole_only=self._starts_like_answer)
                raise ResponseError("oversize", f"response exceeds {MAX_RTU_FRAME} bytes")
            if not self._starts_like_answer:  # the answer may already be whole behind it
                self._skip_noise(bytes(buffer), whole_only=True, complete_after=before)
            return None
        self.leftover = bytes(buffer[expected:]) + bytes(rest)
        del buffer[expected:]
        try:
            return self._check(bytes(buffer))
        except ResponseError as error:
            if error.kind == "crc":
                self._skip_noise(bytes(buffer) + self.leftover, whole_only=self.looks_like_answer)
            raise

    @property
    def looks_like_answer(self) -> bool:
        """True when the frame collected starts like the awaited answer, at its full length.

        Its unit, its function (or that function's exception) and the length those
        imply: with a bad CRC, that is the answer itself damaged on the line, not noise
        in front of it, so no other answer is coming.
        """
        buffer = self._buffer
        return (
            len(buffer) >= 2
            and buffer[0] == self._unit
            and buffer[1] & 0x7F == self._function
            and self._expected == len(buffer)
        )

    def end_of_frame(self) -> RtuFrame:
        """The line went silent: whatever was collected is the whole frame."""
        frame = bytes(self._buffer)
        try:
            return self._check(frame)
        except ResponseError as error:
            if error.kind in ("crc", "short_frame"):
                self._skip_noise(frame, whole_only=self.looks_like_answer)
                if frame and frame[0] != self._unit and len(frame) < MIN_ANSWER:
                    raise ResponseError(
                        "noise", f"{len(frame)} bytes, shorter than any answer"
                    ) from None
            raise

    @property
    def _starts_like_answer(self) -> bool:
        """True unless the first bytes collected are not the awaited unit and function."""
        buffer = self._buffer
        return not buffer or (
            buffer[0] == self._unit and (len(buffer) < 2 or buffer[1] & 0x7F == self._function)
        )

    def _skip_noise(self, data: bytes, *, whole_only: bool, complete_after: int = 0) -> None:
        """Raise ``noise`` when the awaited answer starts behind bytes that came before it.

        A transceiver turning around often puts a byte or two on the line just before
        the slave's answer. ``data`` (all that was collected) is searched for the answer's
        start, the awaited unit and function, within its first ``MAX_NOISE`` bytes; the
        first start that ends a whole frame with a valid CRC, or (unless ``whole_only``)
        that the bytes so far cannot tell yet, is where the answer is taken to begin:
        ``leftover`` is set to start there, for the caller to feed again, and the frame
        must still pass every check then. A frame with the answer's own shape is the
        answer itself, damaged, unless a whole valid answer is found inside it
        (``whole_only``). ``complete_after``: only starts whose frame ends past it are
        checked, so bytes arriving one by one cost each start one CRC at most.
        """
        unit = bytes((self._unit,))
        function = self._function
        start = data.find(unit, 1, MAX_NOISE + 1)
        while start > 0:
            following = start + 1
            if following == len(data) or data[following] & 0x7F == function:
                candidate = data[start:]
                length = response_length(self._request_pdu, candidate)
                if length is not None and 0 < length <= len(candidate):
                    if start + length > complete_after and check_crc(candidate[:length]):
                        self._take_from(candidate, start)
                elif not whole_only:
                    self._take_from(candidate, start)
            start = data.find(unit, following, MAX_NOISE + 1)

    def _take_from(self, candidate: bytes, skipped: int) -> NoReturn:
        """The answer starts ``skipped`` bytes in: the caller feeds ``candidate`` again."""
        self.leftover = candidate
        raise ResponseError("noise", f"{skipped} bytes in front of the answer")

    def reset(self) -> None:
        """Forget a discarded frame and wait for the real answer."""
        self._buffer.clear()
        self._expected = NEED_MORE
        self.leftover = b""

    def _check(self, frame: bytes) -> RtuFrame:
        if len(frame) < MIN_RTU_FRAME:
            raise ResponseError("short_frame", f"response of {len(frame)} bytes is too short")
        if crc16(frame):  # ``check_crc``, inline: the CRC of a frame with its own CRC is 0
            raise ResponseError("crc", "response CRC mismatch")
        if frame[0] != self._unit:
            raise ResponseError(
                "unexpected_unit", f"response from unit {frame[0]}, expected {self._unit}", frame
            )
        if frame[1] & 0x7F != self._function:
            raise ResponseError(
                "unexpected_function",
                f"response for function {frame[1] & 0x7F}, expected {self._function}",
                frame,
            )
        pdu = frame[1:-2]
        if not pdu[0] & fc.EXCEPTION_FLAG:
            mismatch = _mismatch(self._request_pdu, pdu)
            if mismatch:
                raise ResponseError("mismatch", mismatch, frame)
        return _tuple_new(RtuFrame, (frame[0], pdu))  # ``RtuFrame(...)``, minus a Python call


def check_identity(unit: int, function: int, request_pdu: bytes, got_unit: int, pdu: bytes) -> None:
    """Raise ``ResponseError`` unless ``pdu`` from ``got_unit`` can answer the request.

    The checks of ``RtuResponseDecoder._check`` after its CRC (kept inline there: the
    RTU hot path), for the other framings once their checksum is good.
    """
    if got_unit != unit:
        raise ResponseError("unexpected_unit", f"response from unit {got_unit}, expected {unit}")
    if pdu[0] & 0x7F != function:
        raise ResponseError(
            "unexpected_function", f"response for function {pdu[0] & 0x7F}, expected {function}"
        )
    if not pdu[0] & fc.EXCEPTION_FLAG:
        mismatch = _mismatch(request_pdu, pdu)
        if mismatch:
            raise ResponseError("mismatch", mismatch)


_REGISTER_READS: Final = frozenset(
    {fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS, fc.READ_WRITE_MULTIPLE_REGISTERS}
)


def _mismatch(request: bytes, response: bytes) -> str:
    """Why ``response`` cannot answer ``request`` (empty when it can).

    Catches a late answer to an earlier request of the same unit and function:
    its byte count or echoed address differs from what this request asks for.
    """
    function = request[0]
    if function in (fc.READ_COILS, fc.READ_DISCRETE_INPUTS) and len(request) >= 5:
        expected = (((request[3] << 8) | request[4]) + 7) // 8
    elif function in _REGISTER_READS and len(request) >= 5:
        expected = 2 * ((request[3] << 8) | request[4])
    elif function in fc.ECHOED_WRITES:
        if response == fc.write_response(request):
            return ""
        return "response does not echo the request"
    else:
        return ""
    if len(response) < 2 or response[1] != expected:
        return f"byte count does not match the {expected} bytes the request asks for"
    return ""
