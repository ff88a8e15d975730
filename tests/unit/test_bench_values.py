"""The benchmark's register values tell every (unit, address) block apart.

A wrong answer (another request's data under this request's transaction id) is
only visible if the data differs; these blocks are what the load generator
compares byte for byte.
"""

from __future__ import annotations

from bench.values import END_REGISTER, FIRST_REGISTER, register_block, register_value

BLOCK = 3  # the benchmark reads 10; any 3 consecutive registers already identify the block


def test_three_register_blocks_identify_unit_and_address() -> None:
    seen: dict[bytes, tuple[int, int]] = {}
    for unit in range(1, 33):
        for address in range(FIRST_REGISTER, END_REGISTER - BLOCK + 1):
            block = register_block(unit, address, BLOCK)
            assert seen.setdefault(block, (unit, address)) == (unit, address), block.hex()


def test_values_are_16_bit_and_depend_on_the_unit() -> None:
    values = [register_value(unit, 1000) for unit in range(1, 248)]
    assert all(0 <= value <= 0xFFFF for value in values)
    assert len(set(values)) > 200
    assert register_block(1, 1000, 2) == bytes.fromhex(
        f"{register_value(1, 1000):04x}{register_value(1, 1001):04x}"
    )
