"""The gateway end to end: raw Modbus TCP in, a simulated RTU line on a real pty out.

Every expected value is read from, or checked against, the simulated
device's own tables. Synchronisation is by data: a reply that must not come
is followed by one that must, and the first frame read tells which came first.
"""

from __future__ import annotations

import itertools
import os
import select
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from typing import Any

import pytest

from gateway.config import build_config
from gateway.core.rtu import encode_rtu
from gateway.sim import PtyPair, UnitFaults, open_pty_pair, plc, power_controller, zl69x
from gateway.sim.device import pack_bits, pack_registers
from tests.helpers import (
    DEADLINE_S,
    ConnectionClosedError,
    GatewayFactory,
    GatewayOnSim,
    RawClient,
    Reply,
    RunningGateway,
    SimBus,
    h,
    mbap,
    wait_until,
)


def read_pdu(function: int, address: int, quantity: int) -> bytes:
    return struct.pack(">BHH", function, address, quantity)


def registers_reply(function: int, values: Sequence[int]) -> bytes:
    data = pack_registers(values)
    return bytes((function, len(data))) + data


def bits_reply(function: int, values: Sequence[int]) -> bytes:
    data = pack_bits(values)
    return bytes((function, len(data))) + data


def exception(function: int, code: int) -> bytes:
    return bytes((function | 0x80, code))


def identification(function_header: str, objects: dict[int, bytes]) -> bytes:
    body = b"".join(bytes((key, len(value))) + value for key, value in sorted(objects.items()))
    return h(function_header) + bytes((len(objects),)) + body


# --------------------------------------------------------------------------- every function code


def test_reads_of_every_table(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    device = sim.device(1)
    device.holding[2000] = 0xBEEF
    with gw.connect() as client:
        # FC 1 / 2: the Modbus specification's own examples, and the device's tables.
        assert client.request(1, read_pdu(1, 19, 19)) == h("01 03 CD6B05")
        assert client.request(1, read_pdu(1, 19, 19)) == bits_reply(1, device.coils.read(19, 19))
        assert client.request(1, read_pdu(2, 196, 22)) == h("02 03 ACDB35")
        assert client.request(1, read_pdu(2, 196, 22)) == bits_reply(
            2, device.discrete_inputs.read(196, 22)
        )
        # FC 3: the manual's ARR0 example, a whole 125-register block, a value set by the test.
        assert client.request(1, read_pdu(3, 0, 10)) == registers_reply(
            3, [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
        )
        assert client.request(1, read_pdu(3, 1000, 125)) == registers_reply(
            3, list(range(1000, 1125))
        )
        assert client.request(1, read_pdu(3, 2000, 1)) == h("03 02 BEEF")
        # FC 4
        assert client.request(1, read_pdu(4, 8, 1)) == h("04 02 000A")
        assert client.request(1, read_pdu(4, 100, 3)) == registers_reply(
            4, [0x4064, 0x4065, 0x4066]
        )
        # The ZL-69X: 27.5 C and -9.9 C as the vendor document shows, 48 registers at once.
        assert client.request(2, read_pdu(3, 0, 2)) == h("03 04 0113 FF9D")
        assert client.request(2, read_pdu(3, 0, 48)) == registers_reply(
            3, sim.device(2).holding.read(0, 48)
        )
        assert client.request(2, read_pdu(1, 0, 32)) == bits_reply(
            1, sim.device(2).coils.read(0, 32)
        )


def test_single_writes_reach_the_device(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    device = sim.device(1)
    with gw.connect() as client:
        assert client.request(1, h("05 00AC FF00")) == h("05 00AC FF00")  # FC 5 on
        assert device.coils[0xAC] == 1
        assert client.request(1, read_pdu(1, 0xAC, 1)) == h("01 01 01")
        assert client.request(1, h("05 00AC 0000")) == h("05 00AC 0000")  # FC 5 off
        assert device.coils[0xAC] == 0
        assert client.request(1, h("06 0001 1234")) == h("06 0001 1234")  # FC 6
        assert device.holding[1] == 0x1234
        assert client.request(2, h("06 0008 00FA")) == h("06 0008 00FA")  # ZL-69X setpoint
        assert sim.device(2).holding[8] == 250


def test_multiple_writes_reach_the_device(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    device = sim.device(1)
    with gw.connect() as client:
        # FC 15: 9 coils from 6, 1 0 0 0 1 0 0 0 1
        assert client.request(1, h("0F 0006 0009 02 1101")) == h("0F 0006 0009")
        assert device.coils.read(6, 9) == [1, 0, 0, 0, 1, 0, 0, 0, 1]
        # FC 16: 123 registers, the most one request may write.
        values = [(7919 * i) & 0xFFFF for i in range(123)]
        pdu = h("10 0BB8 007B F6") + pack_registers(values)
        assert client.request(1, pdu) == h("10 0BB8 007B")
        assert device.holding.read(3000, 123) == values
        assert client.request(1, read_pdu(3, 3000, 123)) == registers_reply(3, values)
        # FC 22: (current AND 0x00F2) OR (0x0025 AND NOT 0x00F2)
        device.holding[4] = 0x0012
        assert client.request(1, h("16 0004 00F2 0025")) == h("16 0004 00F2 0025")
        assert device.holding[4] == 0x0017
        # FC 23: the write happens before the read, and the read sees it.
        pdu = h("17 000E 0003 000F 0002 04 ABCD 1234")
        assert client.request(1, pdu) == registers_reply(0x17, [0, 0xABCD, 0x1234])
        assert device.holding.read(15, 2) == [0xABCD, 0x1234]
        # FC 16 on the ZL-69X: setpoints 25.5 C and 17.5 C.
        assert client.request(2, h("10 0008 0002 04 00FF 00AF")) == h("10 0008 0002")
        assert sim.device(2).holding.read(8, 2) == [255, 175]


def test_serial_line_functions(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    device = sim.device(1)
    with gw.connect() as client:
        assert client.request(1, h("07")) == h("07 6D")  # FC 7: exception status
        assert client.request(1, h("08 0000 A537")) == h("08 0000 A537")  # FC 8: echo
        # FC 8 / 0x0E: the slave's message count includes this request.
        messages = device.counters.server_messages
        assert client.request(1, h("08 000E 0000")) == h("08 000E") + struct.pack(
            ">H", messages + 1
        )
        # FC 11: the event counter counts successful requests other than FC 11/12.
        events = device.counters.events
        assert client.request(1, h("0B")) == h("0B 0000") + struct.pack(">H", events)
        # FC 12: status, event count, message count, then the newest event first.
        reply = client.request(1, h("0C"))
        assert reply[0] == 0x0C and reply[1] == len(reply) - 2
        status, event_count, message_count = struct.unpack(">HHH", reply[2:8])
        assert (status, event_count) == (0, device.counters.events)
        assert message_count == device.counters.bus_messages
        assert reply[8] == 0x80  # the receive event of this very request
        assert client.request(1, h("11")) == h("11 06") + b"ZQ600" + h("FF")  # FC 17


def test_file_records_and_fifo(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    device = sim.device(1)
    with gw.connect() as client:
        # FC 20: the specification's example: two sub-requests in one.
        reply = client.request(1, h("14 0E 06 0004 0001 0002 06 0003 0009 0002"))
        assert reply == h("14 0C 05 06 0DFE 0020 05 06 33CD 0040")
        assert device.files[4][1:3] == [0x0DFE, 0x0020]
        # FC 21: echoed, and in the file afterwards.
        pdu = h("15 0D 06 0004 0007 0003 06AF 04BE 100D")
        assert client.request(1, pdu) == pdu
        assert device.files[4][7:10] == [0x06AF, 0x04BE, 0x100D]
        # FC 24
        assert client.request(1, h("18 04DE")) == h("18 0006 0002 01B8 1284")


def test_read_device_identification(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    with gw.connect() as client:
        assert client.request(1, h("2B 0E 01 00")) == identification(
            "2B 0E 01 81 00 00",
            {0: b"Nietz Electric", 1: b"ZQ600", 2: b"V1.0.1.1"},
        )
        assert client.request(1, h("2B 0E 04 01")) == identification(
            "2B 0E 04 81 00 00", {1: b"ZQ600"}
        )
        assert client.request(2, h("2B 0E 01 00")) == identification(
            "2B 0E 01 01 00 00",
            {0: b"Companyidentification", 1: b"ZL-69X", 2: b"V2.11"},
        )
    assert sim.stats().crc_errors_in == 0


# --------------------------------------------------------------------------- pipelining


def test_sixteen_pipelined_requests_keep_their_transaction_ids(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)}, server={"max_pipeline": 16})
    # Distinct ids over the whole 16-bit range, distinct addresses, two units, one write.
    tids = [0x0000, 0xFFFF, 0x8000, 0x00FF, 0xFF00, *range(0x1234, 0x1234 + 11)]
    requests: dict[int, tuple[int, bytes, bytes]] = {}
    for index, tid in enumerate(tids):
        if index == 5:
            unit, pdu, expected = 2, read_pdu(3, 8, 2), h("03 04 00FA 00B4")
        elif index == 6:
            unit, pdu = 1, h("06 0010 ABCD")
            expected = pdu
        else:
            address = 1000 + 37 * index
            quantity = 1 + index
            unit, pdu = 1, read_pdu(3, address, quantity)
            expected = registers_reply(3, list(range(address, address + quantity)))
        requests[tid] = (unit, pdu, expected)
    with gw.connect() as client:
        client.send_raw(b"".join(mbap(tid, unit, pdu) for tid, (unit, pdu, _) in requests.items()))
        replies = [client.receive() for _ in tids]
    assert sorted(reply.transaction_id for reply in replies) == sorted(tids)
    for reply in replies:
        unit, _, expected = requests[reply.transaction_id]
        assert (reply.unit, reply.pdu) == (unit, expected), hex(reply.transaction_id)
    assert sim.device(1).holding[0x10] == 0xABCD
    assert sim.stats().requests == 16


def test_concurrent_masters_each_get_their_own_data(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    masters, rounds = 10, 20
    failures: list[str] = []
    start = threading.Barrier(masters)

    def master(index: int) -> None:
        try:
            with gw.connect() as client:
                start.wait(5)
                for round_ in range(rounds):
                    address = 1000 + 500 * index + 7 * round_
                    quantity = 1 + (index + round_) % 20
                    tid = (index << 8) | round_
                    reply = client.request(1, read_pdu(3, address, quantity), tid)
                    expected = registers_reply(3, list(range(address, address + quantity)))
                    if reply != expected:
                        failures.append(f"master {index} round {round_}: {reply.hex()}")
        except (AssertionError, OSError, threading.BrokenBarrierError) as error:
            failures.append(f"master {index}: {error!r}")

    threads = [threading.Thread(target=master, args=(i,)) for i in range(masters)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert not any(thread.is_alive() for thread in threads)
    assert failures == []
    assert sim.stats().requests == masters * rounds


def test_a_deep_pipeline_does_not_starve_another_master(gateway_with: GatewayOnSim) -> None:
    """Round robin between masters, checked by order: the slave counts the messages it served.

    FC 8 sub-function 0x0E returns the slave's message count, this request included, so
    it tells how many of the greedy master's requests were served before each polite one.
    """
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 38400}, server={"max_pipeline": 16})
    greedy_count = 48
    with gw.connect() as greedy, gw.connect() as polite:
        greedy.send_raw(b"".join(mbap(i, 1, read_pdu(3, 1000 + i, 1)) for i in range(greedy_count)))
        first = greedy.receive()
        assert (first.transaction_id, first.pdu) == (0, registers_reply(3, [1000]))
        counts = []
        for _ in range(4):
            reply = polite.request(1, h("08 000E 0000"))
            counts.append(struct.unpack(">H", reply[3:5])[0])
        greedy_replies = [greedy.receive() for _ in range(greedy_count - 1)]
    # With first-come first-served the first polite request would be served after ~16.
    assert counts[0] <= 6, counts
    assert all(b - a <= 4 for a, b in itertools.pairwise(counts)), counts
    assert counts[-1] < greedy_count, "the greedy queue was still deep"
    assert [r.transaction_id for r in greedy_replies] == list(range(1, greedy_count))
    assert all(r.pdu == registers_reply(3, [1000 + r.transaction_id]) for r in greedy_replies)
    assert sim.stats().requests == greedy_count + 4


# --------------------------------------------------------------------------- exceptions


def line_requests(client: RawClient, sim: SimBus, unit: int = 1) -> int:
    """The line's request count after a fence: a read whose answer proves the line caught up."""
    assert client.request(unit, read_pdu(3, 1000, 1)) == h("03 02 03E8")
    return sim.stats().requests


def test_unrouted_unit_is_answered_0x0a_locally(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as client:
        before = line_requests(client, sim)
        tid = client.send(50, read_pdu(3, 0, 1), tid=0xBEEF)
        assert client.receive() == Reply(tid, 50, h("83 0A"))
        assert client.request(247, h("06 0000 0001")) == h("86 0A")
        assert line_requests(client, sim) == before + 1
    assert sim.stats().foreign_frames == 0


def test_silent_slave_is_answered_0x0b_after_the_retries(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        sim={"faults": {1: UnitFaults(silent=True)}},
        line={"timeout": 0.1, "retries": 1},
    )
    with gw.connect() as client:
        assert client.request(1, read_pdu(3, 0, 2)) == h("83 0B")
        assert sim.stats().silent_drops == 2  # the request and one retry
        assert client.request(1, h("06 0000 0001")) == h("86 0B")
        assert sim.stats().silent_drops == 3  # writes are not retried by default
        # The other slave on the line is unaffected.
        assert client.request(2, read_pdu(3, 0, 2)) == h("03 04 0000 0002")


def test_slave_exceptions_pass_through(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2), 3: power_controller(3)})
    cases = [
        (1, read_pdu(3, 9999, 2), "83 02"),  # 9999..10000 passes the end of the PLC's map
        (1, h("18 0001"), "98 02"),  # no FIFO there
        (2, read_pdu(2, 0, 1), "82 01"),  # the ZL-69X has no FC 2
        (2, h("05 0000 FF00"), "85 01"),  # nor FC 5
        (2, h("06 0000 0001"), "86 04"),  # room temperature is read-only
        (2, read_pdu(3, 0, 49), "83 03"),  # it reads at most 48 registers
        (3, read_pdu(3, 0, 6), "83 03"),  # the power controller reads at most 5
    ]
    with gw.connect() as client:
        before = line_requests(client, sim)
        for unit, pdu, expected in cases:
            assert client.request(unit, pdu) == h(expected), (unit, pdu.hex())
        assert line_requests(client, sim) == before + len(cases) + 1


INVALID_REQUESTS = {
    "fc3_126_registers": (read_pdu(3, 0, 126), "83 03"),
    "fc3_0_registers": (read_pdu(3, 0, 0), "83 03"),
    "fc4_126_registers": (read_pdu(4, 0, 126), "84 03"),
    "fc1_2001_bits": (read_pdu(1, 0, 2001), "81 03"),
    "fc3_past_65535": (read_pdu(3, 0xFFFF, 2), "83 02"),
    "fc5_value_1234": (h("05 0000 1234"), "85 03"),
    "fc16_byte_count_mismatch": (h("10 0000 0002 03 0001 02"), "90 03"),
    "fc16_124_registers": (h("10 0000 007C 02 0001"), "90 03"),
    "fc15_1969_coils": (h("0F 0000 07B1 F7") + bytes(247), "8F 03"),
    "fc23_write_122": (h("17 0000 0001 0000 007A 02 0001"), "97 03"),
    "fc3_truncated": (h("03 0000"), "83 03"),
    "exception_code_as_request": (h("83 0000 0001"), "83 01"),
}


@pytest.mark.parametrize(
    ("pdu", "expected"), list(INVALID_REQUESTS.values()), ids=list(INVALID_REQUESTS)
)
def test_invalid_requests_are_answered_locally(
    gateway_with: GatewayOnSim, pdu: bytes, expected: str
) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as client:
        before = line_requests(client, sim)
        assert client.request(1, pdu) == h(expected)
        assert line_requests(client, sim) == before + 1


def test_refused_functions_stay_off_the_line(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, server={"refuse_functions": [8, 17]})
    with gw.connect() as client:
        before = line_requests(client, sim)
        assert client.request(1, h("08 0000 A537")) == h("88 01")
        assert client.request(1, h("11")) == h("91 01")
        assert line_requests(client, sim) == before + 1
        assert client.request(1, h("07")) == h("07 6D")


# --------------------------------------------------------------------------- broadcast


def test_broadcast_reaches_every_slave_and_is_not_answered(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2), 3: zl69x(3)}, line={"broadcast_turnaround": 0.02})
    with gw.connect() as client:
        client.send(0, h("06 0008 0111"), tid=0x0B0B)
        # The next reply on this connection is the following request's: nothing for unit 0.
        tid = client.send(2, read_pdu(3, 8, 1), tid=0x0C0C)
        assert client.receive() == Reply(tid, 2, h("03 02 0111"))
    assert [sim.device(unit).holding[8] for unit in (1, 2, 3)] == [0x0111] * 3
    assert sim.stats().broadcasts == 1


def test_broadcast_reply_when_configured(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        line={"broadcast_turnaround": 0.02},
        server={"broadcast_reply": True},
    )
    with gw.connect() as client:
        tid = client.send(0, h("06 0009 2222"), tid=0x4242)
        assert client.receive() == Reply(tid, 0, h("06 0009 2222"))
        pdu = h("10 0100 0002 04 0A0B 0C0D")
        assert client.request(0, pdu) == h("10 0100 0002")
        assert client.request(1, read_pdu(3, 0x100, 2)) == h("03 04 0A0B 0C0D")
    for unit in (1, 2):
        assert sim.device(unit).holding[9] == 0x2222
        assert sim.device(unit).holding.read(0x100, 2) == [0x0A0B, 0x0C0D]
    assert sim.stats().broadcasts == 2


def test_a_read_cannot_be_broadcast(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, server={"broadcast_reply": True})
    with gw.connect() as client:
        before = line_requests(client, sim)
        assert client.request(0, read_pdu(3, 0, 1)) == h("83 01")
        assert client.request(0, h("07")) == h("87 01")
        assert line_requests(client, sim) == before + 1
    assert sim.stats().broadcasts == 0


# --------------------------------------------------------------------------- a disturbed line


def test_bad_crc_every_time_is_0x0b_after_the_retries(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 0.2, "retries": 2})
    sim.faults(1).crc_error_rate = 1.0
    with gw.connect() as client:
        assert client.request(1, read_pdu(3, 1000, 4)) == h("83 0B")
        stats = sim.stats()
        assert (stats.requests, stats.crc_errors_out) == (3, 3)
        sim.faults(1).crc_error_rate = 0.0
        assert client.request(1, read_pdu(3, 1000, 4)) == registers_reply(3, range(1000, 1004))


def test_bad_crc_half_the_time_is_hidden_by_the_retries(gateway_with: GatewayOnSim) -> None:
    # Seed 0 never corrupts four answers in a row within these 30 requests (21 corrupt in all).
    sim, gw = gateway_with({1: plc(1)}, sim={"seed": 0}, line={"timeout": 0.2, "retries": 3})
    sim.faults(1).crc_error_rate = 0.5
    with gw.connect() as client:
        for index in range(30):
            address = 1000 + 11 * index
            reply = client.request(1, read_pdu(3, address, 3))
            assert reply == registers_reply(3, range(address, address + 3)), index
    stats = sim.stats()
    assert stats.crc_errors_out == 21
    assert stats.requests == 30 + 21


def test_a_late_reply_is_never_taken_for_the_next_answer(gateway_with: GatewayOnSim) -> None:
    """The slave answers 1.2 s late; the gateway gave up after 0.8 s and asked something else.

    A read of another function cannot be confused with the lost answer, so it goes at
    once; the late answer arrives while the gateway waits for it and is thrown away,
    and the real answer, 0.2 s later, is passed on. The slave has shown it is done
    with the lost request: the same read as the lost one is served again at once.
    (Margins of 0.2 s or more, for busy machines.)
    """
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 0.8, "retries": 0})
    sim.faults(1).reply_delay = 1.2
    with gw.connect() as client:
        assert client.request(1, read_pdu(3, 1000, 2)) == h("83 0B")
        # The simulator reads the delay when it serves the next request, right after the
        # late answer: the real one comes 0.2 s later, 0.2 s before the gateway gives up.
        sim.faults(1).reply_delay = 0.2
        reply = client.request(1, read_pdu(4, 2000, 2))
        assert reply == registers_reply(4, [0x4000 + 2000, 0x4000 + 2001])
        sim.faults(1).reply_delay = 0.0
        assert client.request(1, read_pdu(3, 3000, 2)) == registers_reply(3, [3000, 3001])
    assert sim.stats().responses == 3
    discarded = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_discarded_frames_total", {"line": "a", "reason": "unexpected_function"}
    )
    assert discarded == 1


def test_a_read_like_the_lost_one_waits_out_the_late_answer_window(
    gateway_with: GatewayOnSim,
) -> None:
    """After a timeout, a read whose answer looks like the lost one's never reaches the slave
    while that answer may still come: it is answered 0x0B instead of wrong data.

    Unit 2 (another slave) is served meanwhile, and once the window is over the same
    read goes to unit 1 again.
    """
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        line={"timeout": 0.5, "retries": 0, "late_answer_window": 2.5},
    )
    sim.faults(1).reply_delay = 1.3  # its answer arrives 0.8 s after the gateway gave up
    with gw.connect() as client:
        started = time.monotonic()
        assert client.request(1, read_pdu(3, 1000, 2)) == h("83 0B")
        sim.faults(1).reply_delay = 0.0
        # Same function and byte count: it could take the late answer. Held, then 0x0B.
        assert client.request(1, read_pdu(3, 2000, 2)) == h("83 0B")
        assert client.request(2, read_pdu(3, 2000, 2)) == registers_reply(3, [2000, 2001])
        assert sim.stats().requests == 2  # the held read never went on the line
        # Once the window is over the slave is asked again (it is suspect, not dead).
        while time.monotonic() - started < 5.0:
            reply = client.request(1, read_pdu(3, 3000, 2))
            if reply == registers_reply(3, [3000, 3001]):
                break
            assert reply == h("83 0B")
        else:
            pytest.fail("unit 1 was not served again after its late-answer window")
    late = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_late_answer_windows_total", {"line": "a"}
    )
    assert late == 1


class ScriptedSlave:
    """The slave end of a pty driven by the test itself: exact bytes in, exact bytes out."""

    def __init__(self, pair: PtyPair) -> None:
        self.fd = pair.sim_fd

    def read(self, count: int, timeout: float = DEADLINE_S) -> bytes:
        data = bytearray()
        deadline = time.monotonic() + timeout
        while len(data) < count:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"the gateway sent {bytes(data).hex(' ')!r} of {count} bytes"
            if select.select([self.fd], [], [], remaining)[0]:
                data += os.read(self.fd, count - len(data))
        return bytes(data)

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)


ScriptedFactory = Callable[..., tuple[ScriptedSlave, RunningGateway]]


@pytest.fixture
def scripted(make_gateway: GatewayFactory) -> Iterator[ScriptedFactory]:
    """``scripted(**line_options)``: a gateway whose line ``a`` (unit 1, 115200 baud, timeout
    0.5 s, no retry unless given) is driven by the test itself."""
    with ExitStack() as stack:

        def factory(**options: Any) -> tuple[ScriptedSlave, RunningGateway]:
            pair = stack.enter_context(open_pty_pair())
            table = {"device": pair.path, "baudrate": 115200, "units": [1], "timeout": 0.5,
                     "retries": 0, **options}  # fmt: skip
            gw = make_gateway({"lines": {"a": table}})
            stack.callback(gw.stop)  # before the pty closes
            return ScriptedSlave(pair), gw

        yield factory


def test_request_on_the_wire_and_an_answer_in_single_bytes(scripted: ScriptedFactory) -> None:
    slave, gw = scripted()
    pdu = read_pdu(3, 2000, 3)
    with gw.connect() as client:
        tid = client.send(1, pdu, tid=0x1701)
        assert slave.read(8) == h("01 03 07D0 0003 0546")  # unit, PDU, CRC low byte first
        for byte in encode_rtu(1, h("03 06 0001 0002 0003")):
            slave.write(bytes((byte,)))
        assert client.receive() == Reply(tid, 1, h("03 06 0001 0002 0003"))


def test_a_babbling_line_answers_0x0b_then_serves_again(scripted: ScriptedFactory) -> None:
    """A transceiver that never lets the line fall quiet: after noisy_after the waiting
    request is answered 0x0B (nothing was sent: there was no gap), /readyz names the line,
    and service resumes at the first gap."""
    # 600 baud: t3.5 is 64 ms, so a busy machine's scheduling hiccups are no gap.
    slave, gw = scripted(timeout=0.2, noisy_after=0.5, baudrate=600)
    babbling = threading.Event()
    stop = threading.Event()

    def babble() -> None:  # the attacker: a byte every millisecond
        while not stop.is_set():
            slave.write(b"\xff")
            babbling.set()
            time.sleep(0.001)

    thread = threading.Thread(target=babble)
    thread.start()
    try:
        assert babbling.wait(DEADLINE_S)
        with gw.connect() as client:
            started = time.monotonic()
            assert client.request(1, read_pdu(3, 0, 1)) == h("83 0B")
            assert time.monotonic() - started >= 0.45
            ready, why = gw.gateway.is_ready()
            assert ready and why.endswith("noisy line(s), requests answered 0x0B: a"), why
            assert client.request(1, read_pdu(3, 0, 1)) == h("83 0B")  # at once while noisy
    finally:
        stop.set()
        thread.join()
    with gw.connect() as client:
        deadline = time.monotonic() + DEADLINE_S
        while gw.gateway.buses["a"].noisy:
            assert time.monotonic() < deadline, "the line stayed noisy after the babble stopped"
            time.sleep(0.005)
        tid = client.send(1, read_pdu(3, 0, 1))
        assert slave.read(8) == encode_rtu(1, read_pdu(3, 0, 1))
        slave.write(encode_rtu(1, h("03 02 1234")))
        assert client.receive() == Reply(tid, 1, h("03 02 1234"))
    assert gw.gateway.is_ready() == (True, "ok")


@pytest.mark.parametrize(
    "discarded",
    [
        encode_rtu(1, h("03 04 03E8 03E9")),  # a late answer to an earlier, shorter read
        encode_rtu(2, h("03 06 0001 0002 0003")),  # an answer from another unit
    ],
    ids=["late_answer", "other_unit"],
)
def test_a_discarded_frame_and_the_answer_in_one_read(
    scripted: ScriptedFactory, discarded: bytes
) -> None:
    """A USB adapter hands over what arrived within its latency timer (FTDI: 16 ms) at once."""
    slave, gw = scripted()
    with gw.connect() as client:
        tid = client.send(1, read_pdu(3, 2000, 3))
        slave.read(8)
        slave.write(discarded + encode_rtu(1, h("03 06 07D0 07D1 07D2")))
        assert client.receive() == Reply(tid, 1, h("03 06 07D0 07D1 07D2"))


def test_an_answer_right_behind_noise_is_taken_without_a_retry(
    scripted: ScriptedFactory,
) -> None:
    """Noise on the line just before the slave's answer. Retrying at once would put the
    retry on the wire while the answer comes, and the slave's answer to the retry would be
    left over for the next request; the gateway listens on after a garbled frame instead."""
    slave, gw = scripted(retries=1)
    with gw.connect() as client:
        tid = client.send(1, read_pdu(3, 1000, 2))
        slave.read(8)
        slave.write(h("02 03 02 0000 0000"))  # a whole frame with a bad CRC: noise
        slave.write(encode_rtu(1, registers_reply(3, [1000, 1001])))
        assert client.receive() == Reply(tid, 1, registers_reply(3, [1000, 1001]))
        tid = client.send(1, read_pdu(3, 2000, 2))
        assert slave.read(8) == encode_rtu(1, read_pdu(3, 2000, 2))  # no retry of the first
        slave.write(encode_rtu(1, registers_reply(3, [2000, 2001])))
        assert client.receive() == Reply(tid, 1, registers_reply(3, [2000, 2001]))
    crc_errors = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_crc_errors_total", {"line": "a", "unit": "1"}
    )
    assert crc_errors == 1


@pytest.mark.parametrize(
    "fault",
    [
        {"wrong_unit_reply": True},
        {"garbage_before_reply": h("FF 00 55")},
        {"garbage_before_reply": h("01 03 02")},  # the start of a plausible answer
        {"garbage_before_reply": h("01 83")},  # the start of an exception
        {"garbage_before_reply": h("02 03 02 0000 0000")},  # a whole frame, bad CRC
    ],
    ids=["wrong_unit", "noise", "partial_answer", "partial_exception", "bad_crc_frame"],
)
def test_foreign_or_garbled_frames_never_become_wrong_data(
    gateway_with: GatewayOnSim, fault: dict[str, object]
) -> None:
    # A frame from another unit is discarded and the wait goes on; noise in front of the
    # answer is skipped; after a garbled frame the gateway listens on for the answer behind
    # it. Every answer arrives.
    # The simulator leaves t3.5 (1.75 ms) between the garbage and the answer; after a
    # garbled frame of an answer's size (the bad-CRC frame) the gateway listens on for
    # 2 x ``silence``. With the default silence (t3.5) the margin is below what a busy
    # machine delays the simulator's thread by, and the retry then goes out while the
    # answer is still pending (a collision). A 50 ms silence keeps every wait far above
    # scheduling delays; the 2 x t3.5 rule itself is a unit test with literal times.
    line = {"timeout": 1.0, "retries": 1, "silence": 0.05}
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line=line)
    for key, value in fault.items():
        setattr(sim.faults(1), key, value)
    with gw.connect() as client:
        for index in range(6):
            address = 1000 + 13 * index
            reply = client.request(1, read_pdu(3, address, 2))
            assert reply == registers_reply(3, [address, address + 1]), reply.hex()
        # Unit 2, on the same line, still gets its own answers.
        assert client.request(2, read_pdu(3, 1000, 1)) == h("03 02 03E8")
    assert sim.stats().collisions == 0


@pytest.mark.parametrize("noise", [h("FF"), h("00 FE")], ids=["ff", "00_fe"])
@pytest.mark.parametrize("together", [True, False], ids=["one_write", "two_writes"])
def test_noise_from_a_transceiver_turning_around_is_skipped(
    scripted: ScriptedFactory, noise: bytes, together: bool
) -> None:
    """Bytes on the line just before the answer (a driver switching on, a missing bias):
    counted as noise, the answer is taken, nothing is retried."""
    slave, gw = scripted(retries=1)
    answer = encode_rtu(1, registers_reply(3, [1000, 1001]))
    with gw.connect() as client:
        tid = client.send(1, read_pdu(3, 1000, 2))
        slave.read(8)
        if together:
            slave.write(noise + answer)
        else:
            slave.write(noise)
            slave.write(answer)
        assert client.receive() == Reply(tid, 1, registers_reply(3, [1000, 1001]))
        tid = client.send(1, read_pdu(3, 2000, 2))
        assert slave.read(8) == encode_rtu(1, read_pdu(3, 2000, 2))  # no retry of the first
        slave.write(encode_rtu(1, registers_reply(3, [2000, 2001])))
        assert client.receive() == Reply(tid, 1, registers_reply(3, [2000, 2001]))
    sample = gw.gateway.metrics.registry.get_sample_value
    assert sample("modbus_gateway_discarded_frames_total", {"line": "a", "reason": "noise"}) == 1
    assert sample("modbus_gateway_crc_errors_total", {"line": "a", "unit": "1"}) in (None, 0)


# --------------------------------------------------------------------------- masters that misbehave


def test_a_master_leaving_mid_queue_loses_its_queued_requests(gateway_with: GatewayOnSim) -> None:
    """At 4800 baud a one-register read takes ~40 ms: A's queue of 16 cannot drain before A
    leaves, right after its first answer. What A had not sent yet must never reach the line."""
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 4800}, server={"max_pipeline": 16})
    with gw.connect() as a, gw.connect() as b:
        a.send_raw(b"".join(mbap(i, 1, read_pdu(3, 1000 + i, 1)) for i in range(16)))
        assert a.receive() == Reply(0, 1, registers_reply(3, [1000]))
        a.close()
        # B is served, and its answer tells the line is past whatever A had on the wire.
        assert b.request(1, read_pdu(3, 2000, 2)) == registers_reply(3, [2000, 2001])
        requests = sim.stats().requests
        # A's first, the one on the wire when A left, perhaps one more popped meanwhile; B's.
        assert 2 <= requests <= 5, f"{requests - 1} of A's 16 requests reached the line"
        assert b.request(1, read_pdu(3, 2002, 1)) == registers_reply(3, [2002])
    assert sim.stats().requests == requests + 1


def test_a_stop_finishes_the_transaction_on_the_wire_and_answers_the_queue_0x0a(
    gateway_with: GatewayOnSim,
) -> None:
    """A stop waits, within its grace, for the answer on the wire and passes it on; what
    still waits gets 0x0A. The slave takes 1 s, so the stop comes while it works."""
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 3.0})
    sim.faults(1).reply_delay = 1.0
    grace = 5.0
    with gw.connect() as a, gw.connect() as b:
        on_the_wire = a.send(1, read_pdu(3, 1000, 2))
        wait_until(lambda: sim.stats().requests == 1, "the first read on the wire")
        waiting = b.send(1, read_pdu(3, 2000, 2))
        began = time.monotonic()
        gw.stop(grace)
        took = time.monotonic() - began
        assert a.receive() == Reply(on_the_wire, 1, registers_reply(3, [1000, 1001]))
        assert b.receive() == Reply(waiting, 1, exception(3, 0x0A))
    assert took < grace, f"the stop took {took:.2f} s: it waited out its grace"
    assert sim.stats().requests == 1


MALFORMED_HEADERS = {
    "protocol_id_1": mbap(7, 1, read_pdu(3, 0, 1), protocol_id=1),
    "length_0": h("0007 0000 0000 01"),
    "length_1": h("0007 0000 0001 01"),
    "length_300": h("0007 0000 012C 01") + read_pdu(3, 0, 1),
}


@pytest.mark.parametrize("header", list(MALFORMED_HEADERS.values()), ids=list(MALFORMED_HEADERS))
def test_malformed_mbap_closes_that_connection_only(
    gateway_with: GatewayOnSim, header: bytes
) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as good, gw.connect() as bad:
        assert good.request(1, read_pdu(3, 1000, 2)) == registers_reply(3, [1000, 1001])
        assert bad.request(1, read_pdu(3, 1002, 1)) == registers_reply(3, [1002])
        before = sim.stats().requests
        bad.send_raw(header)
        assert bad.is_closed_by_peer(), "the connection stayed open"
        with pytest.raises((ConnectionClosedError, BrokenPipeError, ConnectionResetError)):
            bad.request(1, read_pdu(3, 0, 1))
        for index in range(3):
            address = 1100 + index
            assert good.request(1, read_pdu(3, address, 1)) == registers_reply(3, [address])
        with gw.connect() as fresh:
            assert fresh.request(1, read_pdu(3, 1200, 1)) == registers_reply(3, [1200])
    assert sim.stats().requests == before + 4


def test_requests_split_across_segments_and_glued_together(gateway_with: GatewayOnSim) -> None:
    _, gw = gateway_with({1: plc(1)})
    stream = b"".join(mbap(0x100 + i, 1, read_pdu(3, 1000 + 10 * i, 2)) for i in range(5))
    with gw.connect() as client:
        for offset in range(0, len(stream), 5):  # 5-byte pieces: headers cut anywhere
            client.send_raw(stream[offset : offset + 5])
        replies = sorted((client.receive() for _ in range(5)), key=lambda r: r.transaction_id)
    assert replies == [
        Reply(0x100 + i, 1, registers_reply(3, [1000 + 10 * i, 1001 + 10 * i])) for i in range(5)
    ]


# --------------------------------------------------------------------------- routing


def test_unit_255_routed_to_a_slave_and_unit_100_remapped(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: zl69x(2)},
        routes=[{"unit": 255, "line": "a", "slave": 2}, {"unit": 100, "line": "a", "slave": 1}],
    )
    with gw.connect() as client:
        tid = client.send(255, read_pdu(3, 0, 2))
        assert client.receive() == Reply(tid, 255, h("03 04 0113 FF9D"))  # the ZL-69X's data
        tid = client.send(100, h("06 0020 4321"))
        assert client.receive() == Reply(tid, 100, h("06 0020 4321"))
        assert sim.device(1).holding[0x20] == 0x4321
        assert client.request(100, read_pdu(3, 0, 3)) == registers_reply(3, [0, 2, 4])
        assert client.request(1, read_pdu(3, 0x20, 1)) == h("03 02 4321")
        assert client.request(99, read_pdu(3, 0, 1)) == h("83 0A")
    stats = sim.stats()
    assert (stats.requests, stats.foreign_frames) == (4, 0)  # nothing sent to 100 or 255


def test_unit_255_unrouted_is_0x0a_and_never_on_the_line(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as client:
        before = line_requests(client, sim)
        tid = client.send(255, read_pdu(3, 0, 1), tid=0xFFFF)
        assert client.receive() == Reply(tid, 255, h("83 0A"))
        assert client.request(255, h("11")) == h("91 0A")
        assert line_requests(client, sim) == before + 1
    assert sim.stats().foreign_frames == 0


# --------------------------------------------------------------------------- line timing


def test_t35_is_kept_with_four_masters_hammering_a_19200_baud_line(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2), 3: zl69x(3)}, sim={"baudrate": 19200})
    masters, rounds, depth = 4, 8, 4
    failures: list[str] = []

    def master(index: int) -> None:
        unit = 1 + index % 2
        try:
            with gw.connect() as client:
                for round_ in range(rounds):
                    batch = []
                    for slot in range(depth):
                        address = 1000 + 100 * index + 10 * round_ + slot
                        tid = client.send(unit, read_pdu(3, address, 1 + slot))
                        batch.append((tid, address, 1 + slot))
                    got = {r.transaction_id: r.pdu for r in (client.receive() for _ in batch)}
                    for tid, address, count in batch:
                        expected = registers_reply(3, range(address, address + count))
                        if got.get(tid) != expected:
                            failures.append(f"master {index} tid {tid}: {got.get(tid)!r}")
                setpoints = [250, 180, 20, 400][: index + 1]  # distinct reads: none coalesced
                if client.request(3, read_pdu(3, 8, index + 1)) != registers_reply(3, setpoints):
                    failures.append(f"master {index}: ZL-69X setpoints")
        except (AssertionError, OSError) as error:
            failures.append(f"master {index}: {error!r}")

    threads = [threading.Thread(target=master, args=(i,)) for i in range(masters)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert failures == []
    stats = sim.stats()
    assert stats.requests == masters * (rounds * depth + 1)
    assert (stats.early_requests, stats.collisions, stats.crc_errors_in) == (0, 0, 0)
    assert stats.min_gap_s is not None and stats.min_gap_s >= sim.line.t35


# --------------------------------------------------------------------------- reload


def test_reload_reroutes_without_dropping_the_connection(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: zl69x(2)})
    address = gw.address
    with gw.connect() as client:
        assert client.request(100, read_pdu(3, 0, 1)) == h("83 0A")
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "metrics": {"listen": "off"},
            "lines": {"a": sim.line_table([1, 2])},
            "routes": [{"unit": 100, "line": "a", "slave": 2}],
        }
        gw.run(gw.gateway.reload(build_config(raw, "<reload>")))
        assert client.request(100, read_pdu(3, 0, 1)) == h("03 02 0113")
        assert client.request(1, read_pdu(3, 1000, 1)) == h("03 02 03E8")
    with RawClient(address) as fresh:  # the listener stayed where it was
        assert fresh.request(100, read_pdu(3, 1, 1)) == h("03 02 FF9D")
