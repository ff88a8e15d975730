"""A reply's PDU decoded to what an operator reads: the values, the echo, the exception.

The live trace and the status page show what a slave returned, not only its bytes:
registers of a read (FC 3, 4, 23) and bits of FC 1 and 2, numbered from the request's
start address when the request is known; the echo of a write; an exception's code by
name. Anything else (or anything malformed) yields nothing: the hex still says it all.
"""

from __future__ import annotations

from typing import Any

from .core import pdu as fc
from .core.errors import ExceptionCode

#: The values listed at most per answer (a read returns up to 125 registers or 2000 bits).
MAX_VALUES = 125

_REGISTER_READS = frozenset(
    {fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS, fc.READ_WRITE_MULTIPLE_REGISTERS}
)
_BIT_READS = frozenset({fc.READ_COILS, fc.READ_DISCRETE_INPUTS})


def exception_name(code: int) -> str:
    """``0x02`` → ``"illegal data address"``; an unknown code as ``"exception 0x13"``."""
    try:
        return ExceptionCode(code).name.lower().replace("_", " ")
    except ValueError:
        return f"exception 0x{code:02X}"


def answer_values(request: bytes | None, reply: bytes) -> dict[str, Any] | None:
    """The reply decoded, with ``request`` (its PDU, when known) for addresses and counts."""
    if len(reply) < 2:
        return None
    if fc.is_exception(reply):
        return {"exception": reply[1], "name": exception_name(reply[1])}
    function = reply[0]
    start = _u16(request, 1) if request and request[0] == function and len(request) >= 5 else None
    if function in _REGISTER_READS:
        data = reply[2 : 2 + reply[1]]
        registers = [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data) - 1, 2)]
        return {"address": start, "registers": registers[:MAX_VALUES]}
    if function in _BIT_READS:
        data = reply[2 : 2 + reply[1]]  # a short answer decodes as far as it goes
        count = _u16(request, 3) if start is not None and request else len(data) * 8
        bits = [(data[i // 8] >> (i % 8)) & 1 for i in range(min(count, len(data) * 8))]
        return {"address": start, "bits": bits[: MAX_VALUES * 8]}
    if function in fc.ECHOED_WRITES and len(reply) >= 5:
        return {"address": _u16(reply, 1), "echo": fc.describe_request(reply)}
    return None


def _u16(pdu: bytes | None, offset: int) -> int:
    assert pdu is not None
    return int.from_bytes(pdu[offset : offset + 2], "big")
