"""What every benchmark slave holds, so any answer can be checked against its request.

Holding register ``address`` (1000..9999) of unit ``unit`` holds
``register_value(unit, address)``: a deterministic function of both, with no
per-request nonce, so the slaves need no state shared with the load generator.
Any two blocks of three or more registers read from different (unit, address)
pairs differ (checked for every unit 1..247 once; ``tests/unit/test_bench_values.py``
checks units 1..32), so
an answer delivered to the wrong request (another unit's, or another address's
of the same unit) is a wrong answer the load generator sees. Identical requests
have identical answers: a late answer to an identical read carries right data.

Neither the gateway nor its simulator is imported: the load generator keeps its
own reading of the protocol.
"""

from __future__ import annotations

from collections.abc import Iterable

FIRST_REGISTER = 1000  #: the self-checking block starts here ...
END_REGISTER = 10000  #: ... and ends before this address
_MIX = 0x045D9F3B  # an integer hash's multiplier: neighbouring inputs give unrelated values


def register_value(unit: int, address: int) -> int:
    """The value of holding register ``address`` of ``unit`` (a 16-bit mix of both)."""
    mixed = (unit << 16) | address
    mixed = ((mixed ^ (mixed >> 16)) * _MIX) & 0xFFFFFFFF
    mixed = ((mixed ^ (mixed >> 16)) * _MIX) & 0xFFFFFFFF
    return (mixed ^ (mixed >> 16)) & 0xFFFF


def register_block(unit: int, address: int, quantity: int) -> bytes:
    """The ``quantity`` registers from ``address`` as they travel (big-endian)."""
    return b"".join(
        register_value(unit, register).to_bytes(2, "big")
        for register in range(address, address + quantity)
    )


def identify_block(data: bytes, units: Iterable[int]) -> tuple[int, int] | None:
    """The (unit, address) whose registers ``data`` holds, among ``units``; None if none does."""
    if len(data) < 6 or len(data) % 2:
        return None
    first = int.from_bytes(data[:2], "big")
    quantity = len(data) // 2
    for unit in dict.fromkeys(units):
        for address in range(FIRST_REGISTER, END_REGISTER - quantity + 1):
            if register_value(unit, address) == first and (
                register_block(unit, address, quantity) == data
            ):
                return unit, address
    return None
