"""CRC-16/MODBUS (polynomial 0xA001 reflected, initial value 0xFFFF).

The CRC travels low byte first on the wire. A 256-entry table keeps the cost of
a frame to a few microseconds; the function is pure and allocation-free beyond
its result.
"""

from __future__ import annotations


def _build_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_TABLE = _build_table()


def crc16(data: bytes | bytearray | memoryview) -> int:
    """Return the CRC-16/MODBUS of ``data`` as an integer (low byte is sent first)."""
    crc = 0xFFFF
    table = _TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc16_bytes(data: bytes | bytearray | memoryview) -> bytes:
    """Return the two CRC bytes in wire order (low byte first)."""
    crc = crc16(data)
    return bytes((crc & 0xFF, crc >> 8))


def append_crc(data: bytes | bytearray) -> bytes:
    """Return ``data`` followed by its CRC in wire order."""
    return bytes(data) + crc16_bytes(data)


def check_crc(frame: bytes | bytearray | memoryview) -> bool:
    """True when the last two bytes of ``frame`` are the CRC of the bytes before them."""
    if len(frame) < 3:
        return False
    return crc16(frame) == 0  # the CRC of a frame including its own CRC is zero
