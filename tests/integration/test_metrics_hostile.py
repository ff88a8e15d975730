"""/metrics under hostile input over loopback: label values from remote input are bounded.

A master that sends twenty function codes to every unit id 1..100, while the line's
queue is full, must not grow the exposition past twice its size. Label values a remote
master chooses are bounded: ``unit`` only for a configured slave that answered (else
``other``), ``function`` from the known set (else ``other``), ``outcome`` from a fixed
list; and a ``requests_total`` row gets its whole set of outcomes at 0 only once the
slave answered that function, so what a master sends adds one series per function and
outcome it actually meets.
"""

from __future__ import annotations

import pytest
from prometheus_client.parser import text_string_to_metric_families

from gateway.sim import UnitFaults, plc
from tests.helpers import DEADLINE_S, GatewayFactory, SimFactory
from tests.integration.metrics_harness import exposition

READ_1 = bytes.fromhex("03 0000 0001")
#: Twenty function codes, each a valid request: reads, writes, diagnostics, file records,
#: FIFO, identification, and two the gateway has no name for.
FUNCTIONS = tuple(
    bytes.fromhex(pdu)
    for pdu in (
        "01 0000 0001", "02 0000 0001", "03 0000 0001", "04 0000 0001", "05 0000 FF00",
        "06 0000 0001", "07", "08 0000 1234", "0B", "0C", "0F 0000 0001 01 01",
        "10 0000 0001 02 0001", "11", "14 07 06 0001 0000 0001", "16 0000 FFFF 0000",
        "17 0000 0001 0000 0001 02 0001", "18 0000", "2B 0E 01 00", "41 0000", "64 0000",
    )
)  # fmt: skip


@pytest.mark.slow  # about 3 s or more
def test_twenty_functions_to_a_hundred_units_with_the_queue_full_keep_metrics_within_2x(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1), 2: plc(2)}, faults={2: UnitFaults(silent=True)})
    # Units 1 and 2 routed: 1 answers, 2 is silent and keeps the small queue full.
    table = sim.line_table([1, 2], timeout=0.05, retries=0, max_queue=2, max_queue_per_master=2)
    gw = make_gateway({"lines": {"a": table}, "server": {"max_pipeline": 64}})
    with gw.connect() as master:
        assert master.request(1, READ_1)[0] == 0x03  # an honest poll: the exposition's base
        before = exposition(gw)
        for unit in range(1, 101):
            for pdu in FUNCTIONS:
                master.send(2, READ_1)  # the queue fills behind the silent slave
                master.send(unit, pdu)
            for _ in range(2 * len(FUNCTIONS)):
                master.receive(timeout=DEADLINE_S)
        after = exposition(gw)
    assert len(after) <= 2 * len(before), (len(before), len(after), len(after) / len(before))
    labels = [
        sample.labels
        for family in text_string_to_metric_families(after)
        if family.name == "modbus_gateway_requests"
        for sample in family.samples
    ]
    assert {label["unit"] for label in labels} == {"1", "other"}  # no unit 3..100, nor 2
    assert {label["line"] for label in labels} == {"a", "none"}
    assert len({label["function"] for label in labels}) <= 20  # 19 names and other
