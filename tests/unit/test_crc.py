"""CRC-16/MODBUS against the vendor documents' frames and the catalogue check value."""

from __future__ import annotations

import pytest

from gateway.core.crc import append_crc, check_crc, crc16, crc16_bytes
from tests.helpers import h

# (frame without CRC, CRC bytes in wire order, source)
REFERENCE_CRCS: list[tuple[str, str, str]] = [
    # 000 (ZQ600 manual) 5.3.2 request, printed "01 03 00 00 00 0 A C 5 CD".
    ("01 03 00 00 00 0A", "C5 CD", "000 5.3.2 request"),
    # 001 (power controller sheet): read 3 registers from menu 0.04.
    ("01 03 00 03 00 03", "F5 CB", "001 read command frame"),
    # 001 return frame "01 03 06 00 00 00 B7 0000 9153": 0 V, 18.3 A, 0 W.
    ("01 03 06 00 00 00 B7 00 00", "91 53", "001 return command frame"),
    # 000 5.3.2 response. The document prints 21 data bytes after the byte count 0x14,
    # one stray 00 too many; with exactly the 20 data bytes the byte count announces
    # (registers 0, 2, 4, 6, 8, 10, then four zero registers) the printed CRC 5B 02 checks.
    (
        "01 03 14 0000 0002 0004 0006 0008 000A 0000 0000 0000 0000",
        "5B 02",
        "000 5.3.2 response",
    ),
]


@pytest.mark.parametrize(("body", "crc", "source"), REFERENCE_CRCS)
def test_reference_crc(body: str, crc: str, source: str) -> None:
    assert crc16_bytes(h(body)) == h(crc), source
    assert crc16(h(body)) == int.from_bytes(h(crc), "little")
    assert append_crc(h(body)) == h(body) + h(crc)
    assert check_crc(h(body) + h(crc))


def test_c5cd_as_integer_is_low_byte_first() -> None:
    assert crc16(h("01 03 00 00 00 0A")) == 0xCDC5


def test_printed_000_response_with_stray_byte_does_not_check() -> None:
    printed = h("01 03 14 00 00 00 02 00 04 00 06 00 08 00 0A 00 00 00 00 00 00 00 00 00 5B 02")
    assert len(printed) - 3 - 2 == 21  # one data byte more than the byte count says
    assert not check_crc(printed)


def test_catalogue_check_value() -> None:
    # CRC-16/MODBUS check value from the CRC catalogue: "123456789" -> 0x4B37.
    assert crc16(b"123456789") == 0x4B37
    assert crc16_bytes(b"123456789") == b"\x37\x4b"


def test_empty_input_is_initial_value() -> None:
    assert crc16(b"") == 0xFFFF


def test_accepts_bytearray_and_memoryview() -> None:
    data = h("01 03 00 00 00 0A")
    assert crc16(bytearray(data)) == crc16(memoryview(data)) == 0xCDC5
    assert append_crc(bytearray(data)) == h("01 03 00 00 00 0A C5 CD")


def test_check_crc_rejects_frames_shorter_than_three_bytes() -> None:
    assert not check_crc(b"")
    assert not check_crc(b"\x01")
    # FF FF is the CRC of nothing, so its own CRC is zero: it must still not count as a frame.
    assert crc16(b"\xff\xff") == 0
    assert not check_crc(b"\xff\xff")


def test_check_crc_rejects_swapped_crc_bytes() -> None:
    assert not check_crc(h("01 03 00 00 00 0A CD C5"))


@pytest.mark.parametrize("position", range(8))
def test_check_crc_detects_every_single_byte_corruption(position: int) -> None:
    frame = bytearray(h("01 03 00 00 00 0A C5 CD"))
    frame[position] ^= 0x01
    assert not check_crc(frame)
