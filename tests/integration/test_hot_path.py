"""What a transaction leaves behind: nothing for the garbage collector to find.

Each request the gateway carries is freed by reference counting the moment its
answer is handed back. A reference cycle per transaction (a master's reply
callback holding its own request, say) would leave every answered request for the
cycle collector, whose passes then run every few hundred transactions and cost
the hot path more than the rest of its bookkeeping together.
"""

from __future__ import annotations

import gc

from gateway.core.line import LineRequest
from gateway.sim import plc
from tests.helpers import GatewayOnSim

READ_10 = bytes.fromhex("03 0000 000A")
WRITE_1 = bytes.fromhex("06 0001 0007")
TRANSACTIONS = 60


def _live_requests() -> int:
    return sum(1 for thing in gc.get_objects() if isinstance(thing, LineRequest))


def test_answered_requests_are_freed_without_the_cycle_collector(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1), 2: plc(2)})
    with gw.connect() as master:
        assert master.request(1, READ_10)[0] == 0x03  # warm: connection and line set up
        gc.collect()
        gc.disable()
        try:
            before = _live_requests()
            for index in range(TRANSACTIONS):
                unit = 1 + index % 2
                pdu = WRITE_1 if index % 3 == 0 else READ_10
                assert master.request(unit, pdu)[0] == pdu[0]
            after = _live_requests()
        finally:
            gc.enable()
    assert after - before < TRANSACTIONS // 10, (before, after)
