"""A second master on a real line (a pty): the gateway notices it, says so, and never hands
its answers to a request of its own."""

from __future__ import annotations

import os
import select
import struct
import time
from collections.abc import Iterator

import pytest

from gateway.core.rtu import encode_rtu
from gateway.io.status import LineState
from gateway.sim import PtyPair, open_pty_pair
from tests.helpers import DEADLINE_S, GatewayFactory, RunningGateway, wait_until

READ = struct.pack(">BHH", 3, 0, 2)  # two holding registers: the other master reads the same


def read_exactly(fd: int, count: int) -> bytes:
    """What the gateway wrote on the line, ``count`` bytes of it."""
    data = bytearray()
    deadline = time.monotonic() + DEADLINE_S
    while len(data) < count:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"the gateway wrote {bytes(data).hex(' ')!r} of {count} bytes"
        if select.select([fd], [], [], remaining)[0]:
            data += os.read(fd, count - len(data))
    return bytes(data)


@pytest.fixture
def line(make_gateway: GatewayFactory) -> Iterator[tuple[PtyPair, RunningGateway]]:
    with open_pty_pair() as pair:
        table = {"device": pair.path, "baudrate": 115200, "units": [1], "timeout": 0.5,
                 "retries": 1}  # fmt: skip
        gw = make_gateway({"lines": {"a": table}})
        try:
            yield pair, gw
        finally:
            gw.stop()  # before the pty closes


def test_a_foreign_master_is_named_and_its_answer_is_not_ours(
    line: tuple[PtyPair, RunningGateway],
) -> None:
    pair, gw = line
    bus = gw.gateway.buses["a"]
    assert gw.gateway.is_ready() == (True, "ok")
    os.write(pair.sim_fd, encode_rtu(1, READ))  # another master asks slave 1
    wait_until(lambda: bus.shared, "the line named shared")
    assert gw.gateway.is_ready() == (True, "ok; shared line(s), another master heard: a")
    assert bus.status().state is LineState.SHARED
    counted = gw.gateway.metrics.registry.get_sample_value(
        "modbus_gateway_foreign_master_frames_total", {"line": "a"}
    )
    assert counted == 1
    theirs = encode_rtu(1, bytes.fromhex("0304AAAABBBB"))
    ours = encode_rtu(1, bytes.fromhex("030400010002"))
    os.write(pair.sim_fd, theirs)  # the other master's request is answered: ours may go
    with gw.connect() as client:
        tid = client.send(1, READ)
        assert read_exactly(pair.sim_fd, 8) == encode_rtu(1, READ)
        os.write(pair.sim_fd, encode_rtu(1, READ))  # the other master again, over our wait
        os.write(pair.sim_fd, theirs)  # an answer: whose? The gateway cannot tell
        os.write(pair.sim_fd, ours)  # the other one: both have come, so it asks again
        assert read_exactly(pair.sim_fd, 8) == encode_rtu(1, READ)
        os.write(pair.sim_fd, ours)
        reply = client.receive()
        assert (reply.transaction_id, reply.pdu) == (tid, bytes.fromhex("030400010002"))
