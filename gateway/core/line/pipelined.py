"""The pipelined line: the machine holding a flight wire (see ``flights.py``)."""

from __future__ import annotations

from ..framing import RTU, Framing
from .flights import FlightWire
from .machine import LineCore
from .records import LinePolicy, LineStats


class PipelinedLineCore(LineCore):
    """An MBAP line with up to ``max_in_flight`` attempts outstanding: ``LineCore`` built
    with a ``FlightWire``; it adds nothing else."""

    def __init__(
        self,
        policy: LinePolicy,
        now: float,
        stats: LineStats | None = None,
        framing: Framing = RTU,
        max_in_flight: int = 2,
    ) -> None:
        ids = framing.transaction_ids
        if ids is None:
            raise ValueError(
                f"max_in_flight > 1 needs a framing with transaction ids, not {framing.kind}"
            )
        super().__init__(
            policy, now, stats, framing, FlightWire(ids, max_in_flight, framing.encode)
        )


def new_line_core(
    policy: LinePolicy,
    now: float,
    stats: LineStats | None = None,
    framing: Framing = RTU,
    max_in_flight: int = 1,
) -> LineCore:
    """The line's core: pipelined for an MBAP framing with ``max_in_flight`` > 1; a line
    with ``max_in_flight = 1`` (the default) keeps one attempt at a time."""
    if max_in_flight > 1:
        return PipelinedLineCore(policy, now, stats, framing, max_in_flight)
    return LineCore(policy, now, stats, framing)
