"""Function codes, request validation and exception responses (Modbus Application Protocol v1.1b3).

Theory of operation: ``validate_request`` looks only at the PDU (function code
and data) and raises ``ModbusError`` with the exception code the specification
prescribes when no server could ever accept the request, so the gateway can
answer locally and keep the serial line free. Function codes it does not know
are passed through untouched: the slave is the authority on those.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

from .errors import ExceptionCode, ModbusError

READ_COILS = 0x01
READ_DISCRETE_INPUTS = 0x02
READ_HOLDING_REGISTERS = 0x03
READ_INPUT_REGISTERS = 0x04
WRITE_SINGLE_COIL = 0x05
WRITE_SINGLE_REGISTER = 0x06
READ_EXCEPTION_STATUS = 0x07
DIAGNOSTICS = 0x08
GET_COMM_EVENT_COUNTER = 0x0B
GET_COMM_EVENT_LOG = 0x0C
WRITE_MULTIPLE_COILS = 0x0F
WRITE_MULTIPLE_REGISTERS = 0x10
REPORT_SERVER_ID = 0x11
READ_FILE_RECORD = 0x14
WRITE_FILE_RECORD = 0x15
MASK_WRITE_REGISTER = 0x16
READ_WRITE_MULTIPLE_REGISTERS = 0x17
READ_FIFO_QUEUE = 0x18
ENCAPSULATED_INTERFACE = 0x2B
MEI_READ_DEVICE_ID = 0x0E

EXCEPTION_FLAG = 0x80
MAX_PDU = 253

FUNCTION_NAMES: dict[int, str] = {
    READ_COILS: "read_coils",
    READ_DISCRETE_INPUTS: "read_discrete_inputs",
    READ_HOLDING_REGISTERS: "read_holding_registers",
    READ_INPUT_REGISTERS: "read_input_registers",
    WRITE_SINGLE_COIL: "write_single_coil",
    WRITE_SINGLE_REGISTER: "write_single_register",
    READ_EXCEPTION_STATUS: "read_exception_status",
    DIAGNOSTICS: "diagnostics",
    GET_COMM_EVENT_COUNTER: "get_comm_event_counter",
    GET_COMM_EVENT_LOG: "get_comm_event_log",
    WRITE_MULTIPLE_COILS: "write_multiple_coils",
    WRITE_MULTIPLE_REGISTERS: "write_multiple_registers",
    REPORT_SERVER_ID: "report_server_id",
    READ_FILE_RECORD: "read_file_record",
    WRITE_FILE_RECORD: "write_file_record",
    MASK_WRITE_REGISTER: "mask_write_register",
    READ_WRITE_MULTIPLE_REGISTERS: "read_write_multiple_registers",
    READ_FIFO_QUEUE: "read_fifo_queue",
    ENCAPSULATED_INTERFACE: "encapsulated_interface",
}


#: Writes that the serial-line specification allows to be broadcast (unit 0).
BROADCAST_FUNCTIONS = frozenset(
    {
        WRITE_SINGLE_COIL,
        WRITE_SINGLE_REGISTER,
        WRITE_MULTIPLE_COILS,
        WRITE_MULTIPLE_REGISTERS,
        WRITE_FILE_RECORD,
        MASK_WRITE_REGISTER,
    }
)

#: Plain reads, the ones a cache or coalescing may share between masters.
READ_FUNCTIONS = frozenset(
    {READ_COILS, READ_DISCRETE_INPUTS, READ_HOLDING_REGISTERS, READ_INPUT_REGISTERS}
)


#: Functions without side effects: a timeout or garbled answer may be retried safely.
#: FC 8 only with subfunction 0 (return query data) and FC 43 only as 43/14 (read device
#: identification); see ``is_safe_to_retry``.
SAFE_TO_RETRY = frozenset(
    {
        READ_COILS,
        READ_DISCRETE_INPUTS,
        READ_HOLDING_REGISTERS,
        READ_INPUT_REGISTERS,
        READ_EXCEPTION_STATUS,
        GET_COMM_EVENT_COUNTER,
        GET_COMM_EVENT_LOG,
        REPORT_SERVER_ID,
        READ_FILE_RECORD,
        READ_FIFO_QUEUE,
    }
)


def is_safe_to_retry(pdu: bytes) -> bool:
    """True when sending ``pdu`` twice cannot change the slave (no write, no state change).

    Diagnostics other than subfunction 0 clear counters or restart the port, FC 23
    writes, and user-defined codes may do anything: those are sent once.
    """
    function = pdu[0]
    if function in SAFE_TO_RETRY:
        return True
    if function == DIAGNOSTICS:
        return len(pdu) >= 3 and pdu[1] == 0 and pdu[2] == 0
    if function == ENCAPSULATED_INTERFACE:
        return len(pdu) >= 2 and pdu[1] == MEI_READ_DEVICE_ID
    return False


def function_name(function: int) -> str:
    """A bounded, human-readable name for a function code (``other`` when unknown)."""
    return FUNCTION_NAMES.get(function & 0x7F, "other")


def read_request(function: int, address: int, count: int) -> bytes:
    """The PDU of a read (function 1-4) of ``count`` items from ``address``."""
    return bytes((function, address >> 8, address & 0xFF, count >> 8, count & 0xFF))


def exception_pdu(function: int, code: int) -> bytes:
    """The exception response PDU for ``function``: function | 0x80, then the code."""
    return bytes(((function | EXCEPTION_FLAG) & 0xFF, code))


def _u16(pdu: bytes, offset: int) -> int:
    return (pdu[offset] << 8) | pdu[offset + 1]


def _fail(code: ExceptionCode, reason: str) -> ModbusError:
    return ModbusError(code, reason)


def _need_length(pdu: bytes, length: int, name: str) -> None:
    if len(pdu) != length:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} request PDU must be {length} bytes, got {len(pdu)}",
        )


def _check_quantity(pdu: bytes, name: str, low: int, high: int) -> None:
    """Quantity at offset 3 within [low, high] (exception 0x03)."""
    quantity = _u16(pdu, 3)
    if not low <= quantity <= high:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} quantity {quantity} outside {low}..{high}",
        )


def _check_address(pdu: bytes, name: str) -> None:
    """Address at offset 1 + quantity at offset 3 stays within 0..65535 (exception 0x02)."""
    address = _u16(pdu, 1)
    quantity = _u16(pdu, 3)
    if address + quantity > 0x10000:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_ADDRESS,
            f"{name} address {address} + quantity {quantity} passes 65535",
        )


def _check_range(pdu: bytes, name: str, low: int, high: int) -> None:
    """Quantity within [low, high] first (0x03), then no 16-bit overflow (0x02), as the spec's
    state diagrams order them."""
    _check_quantity(pdu, name, low, high)
    _check_address(pdu, name)


#: The highest quantity of each plain read (FC 1-4), for ``validate_request``'s fast path.
_PLAIN_READ_LIMITS: Final = {
    READ_COILS: 2000,
    READ_DISCRETE_INPUTS: 2000,
    READ_HOLDING_REGISTERS: 125,
    READ_INPUT_REGISTERS: 125,
}


def validate_request(pdu: bytes) -> None:
    """Raise ``ModbusError`` when ``pdu`` cannot be a valid request; return quietly otherwise."""
    if not pdu:
        raise _fail(ExceptionCode.ILLEGAL_FUNCTION, "empty PDU")
    if len(pdu) > MAX_PDU:
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"PDU of {len(pdu)} bytes exceeds {MAX_PDU}")
    function = pdu[0]
    limit = _PLAIN_READ_LIMITS.get(function)
    if limit is not None:  # the common case: the checks inline, the helpers to say why
        if len(pdu) == 5:
            quantity = (pdu[3] << 8) | pdu[4]
            if 1 <= quantity <= limit and ((pdu[1] << 8) | pdu[2]) + quantity <= 0x10000:
                return
        name = function_name(function)
        _need_length(pdu, 5, name)
        _check_range(pdu, name, 1, limit)
        return
    if function == 0 or function & EXCEPTION_FLAG:
        raise _fail(ExceptionCode.ILLEGAL_FUNCTION, f"function code {function} is not a request")
    length = _FIXED_LENGTHS.get(function)
    if length is not None:
        _need_length(pdu, length, function_name(function))
    validate = _VALIDATORS.get(function)
    if validate is not None:  # functions without checks pass: the slave is their authority
        validate(pdu, function_name(function))


def _validate_write_single_coil(pdu: bytes, name: str) -> None:
    value = _u16(pdu, 3)
    if value not in (0x0000, 0xFF00):
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"coil value 0x{value:04X} is not 0xFF00 or 0x0000",
        )


def _validate_diagnostics(pdu: bytes, name: str) -> None:
    if len(pdu) < 3:
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, "diagnostics request lacks a sub-function")


def _validate_encapsulated(pdu: bytes, name: str) -> None:
    if len(pdu) < 2:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE, "encapsulated interface request lacks MEI type"
        )
    if pdu[1] == MEI_READ_DEVICE_ID:
        _need_length(pdu, 4, "read_device_identification")
        if pdu[2] not in (1, 2, 3, 4):
            raise _fail(
                ExceptionCode.ILLEGAL_DATA_VALUE,
                f"read device id code {pdu[2]} outside 1..4",
            )


def _validate_write_multiple(pdu: bytes, name: str, limit: int, *, bits: bool) -> None:
    if len(pdu) < 6:
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"{name} request PDU too short")
    # The specification checks quantity and byte count (0x03) before the address range (0x02).
    _check_quantity(pdu, name, 1, limit)
    quantity = _u16(pdu, 3)
    byte_count = pdu[5]
    expected = (quantity + 7) // 8 if bits else quantity * 2
    if byte_count != expected:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} byte count {byte_count} does not match quantity {quantity} (needs {expected})",
        )
    if len(pdu) != 6 + byte_count:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} carries {len(pdu) - 6} data bytes, byte count says {byte_count}",
        )
    _check_address(pdu, name)


def _validate_file_record(pdu: bytes, name: str, low: int, high: int) -> None:
    if len(pdu) < 2:
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"{name} request lacks a byte count")
    byte_count = pdu[1]
    if not low <= byte_count <= high or len(pdu) != 2 + byte_count:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} byte count {byte_count} invalid for a PDU of {len(pdu)} bytes",
        )
    offset = 2
    while offset < len(pdu):
        if len(pdu) - offset < 7 or pdu[offset] != 6:
            raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"{name} sub-request malformed")
        record_length = _u16(pdu, offset + 5)
        offset += 7
        if name == "write_file_record":
            offset += 2 * record_length
    if offset != len(pdu):
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"{name} record data does not match lengths")


def _validate_read_write(pdu: bytes, name: str) -> None:
    if len(pdu) < 10:
        raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"{name} request PDU too short")
    # The specification checks both quantities and the byte count (0x03) before either
    # address range (0x02).
    _check_quantity(pdu, name, 1, 125)
    write_address = _u16(pdu, 5)
    write_quantity = _u16(pdu, 7)
    if not 1 <= write_quantity <= 121:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} write quantity {write_quantity} outside 1..121",
        )
    byte_count = pdu[9]
    if byte_count != 2 * write_quantity or len(pdu) != 10 + byte_count:
        raise _fail(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"{name} write byte count {byte_count} does not match quantity {write_quantity}",
        )
    _check_address(pdu, name)
    if write_address + write_quantity > 0x10000:
        raise _fail(ExceptionCode.ILLEGAL_DATA_ADDRESS, f"{name} write range passes 65535")


#: Requests whose PDU has one length whatever its content (checked before the rest).
_FIXED_LENGTHS: Final = {
    WRITE_SINGLE_COIL: 5,
    WRITE_SINGLE_REGISTER: 5,
    READ_EXCEPTION_STATUS: 1,
    GET_COMM_EVENT_COUNTER: 1,
    GET_COMM_EVENT_LOG: 1,
    REPORT_SERVER_ID: 1,
    MASK_WRITE_REGISTER: 7,
    READ_FIFO_QUEUE: 3,
}

#: The further checks of each function that has any (``validate_request`` dispatches here).
_VALIDATORS: Final[dict[int, Callable[[bytes, str], None]]] = {
    WRITE_SINGLE_COIL: _validate_write_single_coil,
    DIAGNOSTICS: _validate_diagnostics,
    WRITE_MULTIPLE_COILS: lambda pdu, name: _validate_write_multiple(pdu, name, 1968, bits=True),
    WRITE_MULTIPLE_REGISTERS: lambda pdu, name: _validate_write_multiple(
        pdu, name, 123, bits=False
    ),
    READ_FILE_RECORD: lambda pdu, name: _validate_file_record(pdu, name, 0x07, 0xF5),
    WRITE_FILE_RECORD: lambda pdu, name: _validate_file_record(pdu, name, 0x09, 0xFB),
    READ_WRITE_MULTIPLE_REGISTERS: lambda pdu, name: _validate_read_write(pdu, name),
    ENCAPSULATED_INTERFACE: _validate_encapsulated,
}


#: Writes whose normal response is fixed by the request (see ``write_response``).
ECHOED_WRITES = frozenset(
    {
        WRITE_SINGLE_COIL,
        WRITE_SINGLE_REGISTER,
        WRITE_MULTIPLE_COILS,
        WRITE_MULTIPLE_REGISTERS,
        WRITE_FILE_RECORD,
        MASK_WRITE_REGISTER,
    }
)


def write_response(request: bytes) -> bytes:
    """The normal response to a write in ``ECHOED_WRITES``: the request echoed, or for
    FC 15/16 its function, address and quantity."""
    if request[0] in (WRITE_MULTIPLE_COILS, WRITE_MULTIPLE_REGISTERS):
        return request[:5]
    return request


def is_exception(pdu: bytes) -> bool:
    """True for an exception response PDU."""
    return bool(pdu) and bool(pdu[0] & EXCEPTION_FLAG)


def describe_request(pdu: bytes) -> str:
    """A short human description (``address=0 quantity=10``) for traces and logs."""
    if not pdu:
        return "empty"
    function = pdu[0]
    if (
        function
        in (
            READ_COILS,
            READ_DISCRETE_INPUTS,
            READ_HOLDING_REGISTERS,
            READ_INPUT_REGISTERS,
            WRITE_MULTIPLE_COILS,
            WRITE_MULTIPLE_REGISTERS,
            READ_WRITE_MULTIPLE_REGISTERS,
        )
        and len(pdu) >= 5
    ):
        return f"address={_u16(pdu, 1)} quantity={_u16(pdu, 3)}"
    if function in (WRITE_SINGLE_COIL, WRITE_SINGLE_REGISTER) and len(pdu) >= 5:
        return f"address={_u16(pdu, 1)} value=0x{_u16(pdu, 3):04X}"
    return f"bytes={len(pdu) - 1}"


def describe_response(pdu: bytes) -> str:
    """A short human description of a response PDU for traces."""
    if not pdu:
        return "empty"
    if is_exception(pdu):
        return f"exception=0x{pdu[1]:02X}" if len(pdu) > 1 else "exception"
    function = pdu[0]
    if (
        function
        in (
            READ_COILS,
            READ_DISCRETE_INPUTS,
            READ_HOLDING_REGISTERS,
            READ_INPUT_REGISTERS,
            READ_WRITE_MULTIPLE_REGISTERS,
            GET_COMM_EVENT_LOG,
            REPORT_SERVER_ID,
        )
        and len(pdu) >= 2
    ):
        return f"byte_count={pdu[1]}"
    return f"bytes={len(pdu) - 1}"
