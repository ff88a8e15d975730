"""What a serial line can carry at best: the yardstick utilisation is measured against.

One FC03 transaction of ``quantity`` registers occupies the wire for

    t3.5 + request (8 bytes) + t3.5 + slave turnaround + response (5 + 2 x quantity bytes)

The master keeps t3.5 of silence before its request; the slave, too, needs
t3.5 of silence to know the request has ended before it may answer, and then
takes its own processing time (the "turnaround"). The simulator is run with
``--turnaround`` = t3.5 + the slave's processing time, so it never answers
faster than this model allows and utilisation = achieved / maximum <= 1.
"""

from __future__ import annotations

from dataclasses import dataclass

from gateway.core.timing import character_time, t35

FC03_REQUEST_BYTES = 8  # unit, function, address (2), quantity (2), CRC (2)
SLAVE_PROCESSING_S = 0.0005


def fc03_response_bytes(quantity: int) -> int:
    """Unit, function, byte count, 2 x quantity, CRC."""
    return 5 + 2 * quantity


@dataclass(frozen=True)
class WireBudget:
    """The time one FC03 transaction takes on a line, by part (seconds)."""

    baudrate: int
    request_s: float
    response_s: float
    t35_s: float
    turnaround_s: float

    @property
    def transaction_s(self) -> float:
        """The whole transaction, both t3.5 gaps included."""
        return self.request_s + self.response_s + 2 * self.t35_s + self.turnaround_s

    @property
    def max_per_s(self) -> float:
        """The wire's theoretical maximum, transactions per second."""
        return 1.0 / self.transaction_s

    @property
    def sim_turnaround_s(self) -> float:
        """What to give the simulator's ``--turnaround``: its t3.5 plus its processing."""
        return self.t35_s + self.turnaround_s


def fc03_budget(
    baudrate: int, quantity: int = 10, processing: float = SLAVE_PROCESSING_S
) -> WireBudget:
    """The wire budget of FC03 x ``quantity`` at ``baudrate`` 8N1."""
    char = character_time(baudrate, 8, "N", 1)
    return WireBudget(
        baudrate=baudrate,
        request_s=FC03_REQUEST_BYTES * char,
        response_s=fc03_response_bytes(quantity) * char,
        t35_s=t35(baudrate, 8, "N", 1),
        turnaround_s=processing,
    )
