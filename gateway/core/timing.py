"""Serial-line timing from the line settings (Modbus over Serial Line v1.02, 2.5.1.1).

A character is start + data + parity + stop bits. t1.5 and t3.5 are 1.5 and 3.5
character times, except above 19200 baud where the specification fixes them at
750 us and 1750 us so that the UART's interrupt load stays bounded.
"""

from __future__ import annotations

FIXED_T15_S = 0.000750
FIXED_T35_S = 0.001750
FIXED_TIMING_ABOVE_BAUD = 19200


def bits_per_character(data_bits: int = 8, parity: str = "N", stop_bits: float = 1) -> float:
    """Bits on the wire for one character: start bit, data bits, parity bit, stop bits."""
    return 1 + data_bits + (0 if parity.upper() == "N" else 1) + stop_bits


def character_time(
    baudrate: int, data_bits: int = 8, parity: str = "N", stop_bits: float = 1
) -> float:
    """Seconds one character occupies on the wire."""
    return bits_per_character(data_bits, parity, stop_bits) / baudrate


def transmission_time(
    nbytes: int, baudrate: int, data_bits: int = 8, parity: str = "N", stop_bits: float = 1
) -> float:
    """Seconds ``nbytes`` characters occupy on the wire, back to back."""
    return nbytes * character_time(baudrate, data_bits, parity, stop_bits)


def t15(baudrate: int, data_bits: int = 8, parity: str = "N", stop_bits: float = 1) -> float:
    """Longest silence allowed inside a frame, in seconds."""
    if baudrate > FIXED_TIMING_ABOVE_BAUD:
        return FIXED_T15_S
    return 1.5 * character_time(baudrate, data_bits, parity, stop_bits)


def t35(baudrate: int, data_bits: int = 8, parity: str = "N", stop_bits: float = 1) -> float:
    """Shortest silence between two frames, in seconds."""
    if baudrate > FIXED_TIMING_ABOVE_BAUD:
        return FIXED_T35_S
    return 3.5 * character_time(baudrate, data_bits, parity, stop_bits)
