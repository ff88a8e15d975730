"""Request validation: every limit of the Modbus Application Protocol v1.1b3 at its boundary.

The specification's state diagrams check quantities and byte counts first (exception 0x03)
and the address range after (0x02); requests with both faults must get 0x03.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.errors import ExceptionCode, ModbusError, ProtocolError
from gateway.core.pdu import (
    describe_request,
    describe_response,
    exception_pdu,
    function_name,
    is_exception,
    validate_request,
    write_response,
)
from tests.helpers import h, read

ILLEGAL_FUNCTION = ExceptionCode.ILLEGAL_FUNCTION
ILLEGAL_ADDRESS = ExceptionCode.ILLEGAL_DATA_ADDRESS
ILLEGAL_VALUE = ExceptionCode.ILLEGAL_DATA_VALUE


def u16(value: int) -> bytes:
    return value.to_bytes(2, "big")


def write_coils(address: int, quantity: int, byte_count: int | None = None) -> bytes:
    count = (quantity + 7) // 8 if byte_count is None else byte_count
    return bytes((0x0F,)) + u16(address) + u16(quantity) + bytes((count & 0xFF,)) + bytes(count)


def write_registers(address: int, quantity: int, byte_count: int | None = None) -> bytes:
    count = 2 * quantity if byte_count is None else byte_count
    return bytes((0x10,)) + u16(address) + u16(quantity) + bytes((count & 0xFF,)) + bytes(count)


def read_write(
    read_address: int,
    read_quantity: int,
    write_address: int,
    write_quantity: int,
    byte_count: int | None = None,
) -> bytes:
    count = 2 * write_quantity if byte_count is None else byte_count
    return (
        bytes((0x17,))
        + u16(read_address)
        + u16(read_quantity)
        + u16(write_address)
        + u16(write_quantity)
        + bytes((count & 0xFF,))
        + bytes(count)
    )


def read_file(*subrequests: tuple[int, int, int, int]) -> bytes:
    body = b"".join(
        bytes((kind,)) + u16(file) + u16(record) + u16(length)
        for kind, file, record, length in subrequests
    )
    return bytes((0x14, len(body))) + body


def write_file(*subrequests: tuple[int, int, int, int]) -> bytes:
    body = b"".join(
        bytes((kind,)) + u16(file) + u16(record) + u16(length) + bytes(2 * length)
        for kind, file, record, length in subrequests
    )
    return bytes((0x15, len(body) & 0xFF)) + body


def code_of(pdu: bytes) -> ExceptionCode | None:
    try:
        validate_request(pdu)
    except ModbusError as error:
        assert isinstance(error, ProtocolError)
        assert error.kind == "invalid_request"
        return error.code
    return None


VALID: list[tuple[str, bytes]] = [
    # vendor document 004 examples
    ("004 fc02", h("02 0006 0012")),
    ("004 fc03", h("03 0002 0003")),
    ("004 fc04", h("04 0006 0002")),
    ("004 fc05", h("05 0012 FF00")),
    ("004 fc06", h("06 0007 1234")),
    ("004 fc15", h("0F 0006 0009 02 11 01")),
    ("004 fc16", h("10 0002 0003 06 1122 3344 5566")),
    # vendor documents 000 / 001 / 003
    ("000 fc03", h("03 0000 000A")),
    ("001 fc03", h("03 0003 0003")),
    ("003 fc03", h("03 0001 0015")),
    # reads: 1..2000 bits, 1..125 registers, up to the last address
    ("fc01 min", read(0, 1, 0x01)),
    ("fc01 max", read(0, 2000, 0x01)),
    ("fc02 max", read(0, 2000, 0x02)),
    ("fc01 top", read(0x10000 - 2000, 2000, 0x01)),
    ("fc02 last", read(0xFFFF, 1, 0x02)),
    ("fc03 min", read(0, 1, 0x03)),
    ("fc03 max", read(0, 125, 0x03)),
    ("fc04 max", read(0, 125, 0x04)),
    ("fc03 top", read(0x10000 - 125, 125, 0x03)),
    ("fc04 last", read(0xFFFF, 1, 0x04)),
    # single writes
    ("fc05 on", h("05 FFFF FF00")),
    ("fc05 off", h("05 0000 0000")),
    ("fc06 any", h("06 FFFF FFFF")),
    # writes: 1..1968 bits, 1..123 registers
    ("fc15 min", write_coils(0, 1)),
    ("fc15 max", write_coils(0, 1968)),
    ("fc15 top", write_coils(0x10000 - 1968, 1968)),
    ("fc15 last", write_coils(0xFFFF, 1)),
    ("fc16 min", write_registers(0, 1)),
    ("fc16 max", write_registers(0, 123)),
    ("fc16 top", write_registers(0x10000 - 123, 123)),
    # FC23: read 1..125, write 1..121
    ("fc23 spec", h("17 0003 0006 000E 0003 06 00FF 00FF 00FF")),
    ("fc23 min", read_write(0, 1, 0, 1)),
    ("fc23 max", read_write(0, 125, 0, 121)),
    ("fc23 top", read_write(0x10000 - 125, 125, 0x10000 - 121, 121)),
    # one-byte requests
    ("fc07", h("07")),
    ("fc11", h("0B")),
    ("fc12", h("0C")),
    ("fc17", h("11")),
    # diagnostics: sub-function and data
    ("fc08 echo", h("08 0000 A537")),
    ("fc08 bare", h("08 000A")),
    # file records
    ("fc20 spec", h("14 0E 06 0004 0001 0002 06 0003 0009 0002")),
    ("fc20 min", read_file((6, 1, 0, 1))),
    ("fc20 max", read_file(*[(6, 1, n, 1) for n in range(35)])),  # 35 x 7 = 0xF5 bytes
    ("fc21 spec", h("15 0D 06 0004 0007 0003 06AF 04BE 100D")),
    ("fc21 min", write_file((6, 1, 0, 1))),  # 9 bytes
    ("fc21 max", write_file((6, 1, 0, 122))),  # 7 + 244 = 0xFB bytes
    # others
    ("fc22", h("16 0004 00F2 0025")),
    ("fc24", h("18 04DE")),
    ("fc43/14 basic", h("2B 0E 01 00")),
    ("fc43/14 individual", h("2B 0E 04 80")),
    ("fc43/13 canopen", h("2B 0D 00 00 00")),
    ("fc43 other mei", h("2B 01")),
    # unknown function codes pass to the slave, which is the authority on them
    ("fc65 user", h("41 01 02 03")),
    ("fc9 bare", h("09")),
    ("fc127 max size", bytes((0x7F,)) + bytes(252)),
]


@pytest.mark.parametrize("pdu", [pdu for _, pdu in VALID], ids=[name for name, _ in VALID])
def test_valid_requests_pass(pdu: bytes) -> None:
    assert code_of(pdu) is None


INVALID: list[tuple[str, bytes, ExceptionCode]] = [
    # not a request at all
    ("empty", b"", ILLEGAL_FUNCTION),
    ("function 0", h("00 0000 0001"), ILLEGAL_FUNCTION),
    ("exception 0x83", h("83 02"), ILLEGAL_FUNCTION),
    ("function 0x80", h("80"), ILLEGAL_FUNCTION),
    ("function 0xFF", h("FF 00"), ILLEGAL_FUNCTION),
    ("over 253 bytes", bytes((0x41,)) + bytes(253), ILLEGAL_VALUE),
    # read bits: quantity 1..2000
    ("fc01 qty 0", read(0, 0, 0x01), ILLEGAL_VALUE),
    ("fc01 qty 2001", read(0, 2001, 0x01), ILLEGAL_VALUE),
    ("fc02 qty 0", read(0, 0, 0x02), ILLEGAL_VALUE),
    ("fc02 qty 2001", read(0, 2001, 0x02), ILLEGAL_VALUE),
    ("fc01 qty 0xFFFF", read(0, 0xFFFF, 0x01), ILLEGAL_VALUE),
    ("fc01 past top", read(0x10000 - 1999, 2000, 0x01), ILLEGAL_ADDRESS),
    ("fc02 last+1", read(0xFFFF, 2, 0x02), ILLEGAL_ADDRESS),
    ("fc01 qty before address", read(0xFFFF, 2001, 0x01), ILLEGAL_VALUE),
    ("fc01 short", h("01 0000 00"), ILLEGAL_VALUE),
    ("fc01 long", h("01 0000 0001 00"), ILLEGAL_VALUE),
    # read registers: quantity 1..125
    ("fc03 qty 0", read(0, 0, 0x03), ILLEGAL_VALUE),
    ("fc03 qty 126", read(0, 126, 0x03), ILLEGAL_VALUE),
    ("fc04 qty 0", read(0, 0, 0x04), ILLEGAL_VALUE),
    ("fc04 qty 126", read(0, 126, 0x04), ILLEGAL_VALUE),
    ("fc03 past top", read(0x10000 - 124, 125, 0x03), ILLEGAL_ADDRESS),
    ("fc04 last+1", read(0xFFFF, 2, 0x04), ILLEGAL_ADDRESS),
    ("fc03 short", h("03 0000"), ILLEGAL_VALUE),
    ("fc03 only function", h("03"), ILLEGAL_VALUE),
    # FC5: value 0xFF00 or 0x0000
    ("fc05 0x0001", h("05 0000 0001"), ILLEGAL_VALUE),
    ("fc05 0x00FF", h("05 0000 00FF"), ILLEGAL_VALUE),
    ("fc05 0xFF01", h("05 0000 FF01"), ILLEGAL_VALUE),
    ("fc05 0xFFFF", h("05 0000 FFFF"), ILLEGAL_VALUE),
    ("fc05 0x0100", h("05 0000 0100"), ILLEGAL_VALUE),
    ("fc05 short", h("05 0000 FF"), ILLEGAL_VALUE),
    ("fc06 short", h("06 0000 12"), ILLEGAL_VALUE),
    ("fc06 long", h("06 0000 1234 56"), ILLEGAL_VALUE),
    # FC15: quantity 1..1968, byte count = ceil(quantity / 8), data matches byte count
    ("fc15 qty 0", write_coils(0, 0), ILLEGAL_VALUE),
    ("fc15 qty 1969", write_coils(0, 1969), ILLEGAL_VALUE),
    ("fc15 count low", write_coils(0, 9, byte_count=1), ILLEGAL_VALUE),
    ("fc15 count high", write_coils(0, 8, byte_count=2), ILLEGAL_VALUE),
    ("fc15 missing data", h("0F 0006 0009 02 11"), ILLEGAL_VALUE),
    ("fc15 extra data", h("0F 0006 0009 02 11 01 00"), ILLEGAL_VALUE),
    ("fc15 short", h("0F 0006 0009"), ILLEGAL_VALUE),
    ("fc15 past top", write_coils(0x10000 - 1967, 1968), ILLEGAL_ADDRESS),
    ("fc15 last+1", write_coils(0xFFFF, 2), ILLEGAL_ADDRESS),
    ("fc15 count before address", write_coils(0xFFFF, 9, byte_count=1), ILLEGAL_VALUE),
    ("fc15 data before address", h("0F FFFF 0009 02 11"), ILLEGAL_VALUE),
    # FC16: quantity 1..123, byte count = 2 x quantity
    ("fc16 qty 0", write_registers(0, 0), ILLEGAL_VALUE),
    ("fc16 qty 124", write_registers(0, 124), ILLEGAL_VALUE),
    ("fc16 count odd", write_registers(0, 3, byte_count=5), ILLEGAL_VALUE),
    ("fc16 count high", write_registers(0, 3, byte_count=8), ILLEGAL_VALUE),
    ("fc16 missing data", h("10 0002 0003 06 1122 3344 55"), ILLEGAL_VALUE),
    ("fc16 past top", write_registers(0x10000 - 122, 123), ILLEGAL_ADDRESS),
    ("fc16 last+1", write_registers(0xFFFF, 2), ILLEGAL_ADDRESS),
    ("fc16 count before address", write_registers(0xFFFF, 2, byte_count=2), ILLEGAL_VALUE),
    # FC23: read 1..125, write 1..121, byte count = 2 x write quantity
    ("fc23 read 0", read_write(0, 0, 0, 1), ILLEGAL_VALUE),
    ("fc23 read 126", read_write(0, 126, 0, 1), ILLEGAL_VALUE),
    ("fc23 write 0", read_write(0, 1, 0, 0), ILLEGAL_VALUE),
    ("fc23 write 122", read_write(0, 1, 0, 122), ILLEGAL_VALUE),
    ("fc23 count low", read_write(0, 1, 0, 2, byte_count=2), ILLEGAL_VALUE),
    ("fc23 missing data", read_write(0, 1, 0, 2)[:-1], ILLEGAL_VALUE),
    ("fc23 short", h("17 0000 0001 0000 0001"), ILLEGAL_VALUE),
    ("fc23 read past top", read_write(0x10000 - 124, 125, 0, 1), ILLEGAL_ADDRESS),
    ("fc23 write past top", read_write(0, 1, 0x10000 - 120, 121), ILLEGAL_ADDRESS),
    ("fc23 write qty before read address", read_write(0xFFFF, 2, 0, 122), ILLEGAL_VALUE),
    ("fc23 count before read address", read_write(0xFFFF, 2, 0, 2, byte_count=2), ILLEGAL_VALUE),
    # one-byte requests carry nothing else
    ("fc07 long", h("07 00"), ILLEGAL_VALUE),
    ("fc11 long", h("0B 00"), ILLEGAL_VALUE),
    ("fc12 long", h("0C 00"), ILLEGAL_VALUE),
    ("fc17 long", h("11 00"), ILLEGAL_VALUE),
    # diagnostics needs a sub-function
    ("fc08 bare", h("08"), ILLEGAL_VALUE),
    ("fc08 half", h("08 00"), ILLEGAL_VALUE),
    # file records: byte count 0x07..0xF5 (read), 0x09..0xFB (write), reference type 6
    ("fc20 no count", h("14"), ILLEGAL_VALUE),
    ("fc20 count 6", h("14 06 06 0001 0000 00"), ILLEGAL_VALUE),
    ("fc20 count 0xF6", read_file(*[(6, 1, n, 1) for n in range(35)]) + b"\x00", ILLEGAL_VALUE),
    ("fc20 count vs data", h("14 07 06 0001 0000 0001 00"), ILLEGAL_VALUE),
    ("fc20 not 7 per sub-request", h("14 08 06 0001 0000 0001 00"), ILLEGAL_VALUE),
    ("fc20 reference type 5", read_file((5, 1, 0, 1)), ILLEGAL_VALUE),
    ("fc21 count 8", h("15 08 06 0001 0000 0000 00"), ILLEGAL_VALUE),
    ("fc21 count 0xFC", write_file((6, 1, 0, 122)) + b"\x00", ILLEGAL_VALUE),
    ("fc21 record length vs data", h("15 0B 06 0001 0000 0001 1234 56 78"), ILLEGAL_VALUE),
    ("fc21 reference type 0", write_file((0, 1, 0, 1)), ILLEGAL_VALUE),
    # mask write, FIFO
    ("fc22 short", h("16 0004 00F2 00"), ILLEGAL_VALUE),
    ("fc22 long", h("16 0004 00F2 0025 00"), ILLEGAL_VALUE),
    ("fc24 short", h("18 04"), ILLEGAL_VALUE),
    ("fc24 long", h("18 04DE 00"), ILLEGAL_VALUE),
    # encapsulated interface / read device identification
    ("fc43 no mei", h("2B"), ILLEGAL_VALUE),
    ("fc43/14 code 0", h("2B 0E 00 00"), ILLEGAL_VALUE),
    ("fc43/14 code 5", h("2B 0E 05 00"), ILLEGAL_VALUE),
    ("fc43/14 short", h("2B 0E 01"), ILLEGAL_VALUE),
    ("fc43/14 long", h("2B 0E 01 00 00"), ILLEGAL_VALUE),
]


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [(pdu, code) for _, pdu, code in INVALID],
    ids=[name for name, _, _ in INVALID],
)
def test_invalid_requests_get_the_specified_exception(pdu: bytes, expected: ExceptionCode) -> None:
    assert code_of(pdu) == expected


def test_error_carries_reason_text() -> None:
    with pytest.raises(ModbusError) as caught:
        validate_request(read(0, 126, 0x03))
    assert caught.value.code is ExceptionCode.ILLEGAL_DATA_VALUE
    assert "126" in caught.value.reason
    assert str(caught.value) == caught.value.reason


# ---- exception responses and helpers --------------------------------------------------


@pytest.mark.parametrize(
    ("function", "code", "expected"),
    [
        (0x03, 0x02, "83 02"),
        (0x01, 0x01, "81 01"),
        (0x10, 0x0A, "90 0A"),
        (0x2B, 0x0B, "AB 0B"),
        (0x83, 0x04, "83 04"),  # already flagged: stays one byte
        (0x7F, 0x03, "FF 03"),
    ],
)
def test_exception_pdu(function: int, code: int, expected: str) -> None:
    assert exception_pdu(function, code) == h(expected)
    assert is_exception(exception_pdu(function, code))


def test_exception_codes_have_the_specified_values() -> None:
    assert [int(code) for code in ExceptionCode] == [1, 2, 3, 4, 5, 6, 8, 0x0A, 0x0B]


def test_is_exception() -> None:
    assert not is_exception(b"")
    assert not is_exception(h("03 02 0000"))
    assert is_exception(h("90 0A"))


@pytest.mark.parametrize(
    ("function", "name"),
    [
        (0x03, "read_holding_registers"),
        (0x83, "read_holding_registers"),
        (0x10, "write_multiple_registers"),
        (0x17, "read_write_multiple_registers"),
        (0x2B, "encapsulated_interface"),
        (0x41, "other"),
        (0x00, "other"),
    ],
)
def test_function_name(function: int, name: str) -> None:
    assert function_name(function) == name


def test_describe() -> None:
    assert describe_request(h("03 0000 000A")) == "address=0 quantity=10"
    assert describe_request(h("05 0012 FF00")) == "address=18 value=0xFF00"
    assert describe_request(h("07")) == "bytes=0"
    assert describe_request(b"") == "empty"
    assert describe_response(h("03 14") + bytes(20)) == "byte_count=20"
    assert describe_response(h("83 02")) == "exception=0x02"
    assert describe_response(h("06 0007 1234")) == "bytes=4"
    assert describe_response(b"") == "empty"


def test_the_normal_response_to_a_write() -> None:
    assert write_response(h("06 0007 1234")) == h("06 0007 1234")
    assert write_response(h("10 0001 0002 04 000A 0102")) == h("10 0001 0002")
    assert write_response(h("0F 0013 000A 02 CD01")) == h("0F 0013 000A")


@given(
    function=st.sampled_from([0x01, 0x02, 0x03, 0x04]),
    address=st.integers(0, 0xFFFF),
    quantity=st.integers(0, 0xFFFF),
    extra=st.sampled_from([b"", b"\x00"]),
)
def test_every_plain_read_is_judged_as_the_specification_says(
    function: int, address: int, quantity: int, extra: bytes
) -> None:
    """FC 1-4: length 5, then quantity (0x03: 1..2000 bits or 1..125 registers), then
    address + quantity within 65536 (0x02); whichever path the check takes."""
    pdu = bytes((function,)) + address.to_bytes(2, "big") + quantity.to_bytes(2, "big") + extra
    limit = 2000 if function <= 0x02 else 125
    if extra or not 1 <= quantity <= limit:
        expected: ExceptionCode | None = ExceptionCode.ILLEGAL_DATA_VALUE
    elif address + quantity > 0x10000:
        expected = ExceptionCode.ILLEGAL_DATA_ADDRESS
    else:
        expected = None
    if expected is None:
        validate_request(pdu)
    else:
        with pytest.raises(ModbusError) as raised:
            validate_request(pdu)
        assert raised.value.code == expected
