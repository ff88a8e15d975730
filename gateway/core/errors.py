"""Typed protocol errors, each carrying what the gateway should do about it.

A ``ModbusError`` is a request the gateway answers itself with a Modbus
exception code; a ``FramingError`` is a byte stream that cannot be trusted any
more (the TCP connection that sent it is closed); a ``ResponseError`` is an
RTU answer that must not be passed on.
"""

from __future__ import annotations

from enum import IntEnum


class ExceptionCode(IntEnum):
    """Modbus exception codes (Modbus Application Protocol v1.1b3, section 7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    ACKNOWLEDGE = 0x05
    SERVER_DEVICE_BUSY = 0x06
    MEMORY_PARITY_ERROR = 0x08
    GATEWAY_PATH_UNAVAILABLE = 0x0A
    GATEWAY_TARGET_FAILED = 0x0B


class ProtocolError(Exception):
    """Base of every error the core raises about bytes it was given."""

    kind: str = "protocol"


class ModbusError(ProtocolError):
    """A request the gateway must answer locally with an exception code."""

    kind = "invalid_request"

    def __init__(self, code: ExceptionCode, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


class FramingError(ProtocolError):
    """A TCP byte stream that can no longer be split into frames; close the connection."""

    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason


class ResponseError(ProtocolError):
    """An RTU response that is not a valid answer to the request on the wire.

    ``frame`` is the whole checked frame when it was intact but answers something else
    (another unit, function or request): it may be a late answer the line still expects.
    """

    def __init__(self, kind: str, reason: str, frame: bytes = b"") -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason
        self.frame = frame
