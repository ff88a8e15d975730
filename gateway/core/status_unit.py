"""The status unit (agent mode): a unit id the gateway answers itself with each poll
block's freshness.

Theory of operation. With ``polling.status_unit`` set, block *N* of the configuration
(``[[poll]]`` entries in order) is two holding and input registers: *2N*, the age of the
block's data in tenths of a second (65535: never polled; it saturates there), and *2N+1*,
its state (0 fresh, 1 stale, 2 failing; ``BlockState.code``). The block computes both
(``PollBlock.status_registers``); this module only answers a read of them.

A request reaches the status unit through the same admission as any request (routing,
the access rules, the gateway's refusals, validation), which routes the unit to a line
named ``STATUS_LINE``: this is what that line answers. FC 3 and FC 4 get the registers;
a range past the last block's registers gets exception 02, a count outside 1..125 (or a
read of the wrong length) 03, any other function, writes included, 01.

Invariants: ``status_answer`` is total (any PDU: an answer, never an exception raised),
pure (``now`` comes in), and reads only the blocks the range covers.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, Protocol

from . import pdu as fc
from .errors import ExceptionCode

#: The line the routing table sends the status unit to, and the ``line`` label of its
#: answers in ``requests_total`` and the request latency (no real line may take the name).
STATUS_LINE: Final = "status"
#: The registers of one block.
REGISTERS_PER_BLOCK: Final = 2
#: The most registers one read may ask for (FC 3 and FC 4).
MAX_REGISTERS: Final = 125

_READS: Final = frozenset({fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS})


class BlockFreshness(Protocol):
    """What the status unit reads of one poll block (``core.line.polling.PollBlock``)."""

    def status_registers(self, now: float) -> tuple[int, int]: ...


def status_answer(pdu: bytes, blocks: Sequence[BlockFreshness], now: float) -> bytes:
    """The status unit's answer PDU to ``pdu``, with ``blocks`` in configuration order."""
    function = pdu[0] if pdu else 0
    if function not in _READS:
        return fc.exception_pdu(function, ExceptionCode.ILLEGAL_FUNCTION)
    if len(pdu) != 5:
        return fc.exception_pdu(function, ExceptionCode.ILLEGAL_DATA_VALUE)
    address = (pdu[1] << 8) | pdu[2]
    count = (pdu[3] << 8) | pdu[4]
    if not 1 <= count <= MAX_REGISTERS:
        return fc.exception_pdu(function, ExceptionCode.ILLEGAL_DATA_VALUE)
    if address + count > REGISTERS_PER_BLOCK * len(blocks):
        return fc.exception_pdu(function, ExceptionCode.ILLEGAL_DATA_ADDRESS)
    first = address // REGISTERS_PER_BLOCK
    last = (address + count - 1) // REGISTERS_PER_BLOCK
    values: list[int] = []
    for block in blocks[first : last + 1]:
        values.extend(block.status_registers(now))
    skip = address - REGISTERS_PER_BLOCK * first
    data = b"".join(value.to_bytes(2, "big") for value in values[skip : skip + count])
    return bytes((function, 2 * count)) + data
