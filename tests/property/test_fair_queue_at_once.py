"""A request that goes at once keeps the fair queue's accounts as queuing it would.

The line machine sends a request that finds the line free and nothing waiting without
putting it through the fair queue (the usual case of one master polling a line). The
accounts must come out as if it had been queued and chosen at once: a master that went
that way must not gain or lose a turn against the others later.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.line.fair_queue import FairQueue, Master
from gateway.core.line.records import LineRequest, LineStats
from tests.helpers import read

times = st.floats(min_value=0.0, max_value=10.0, allow_nan=False)
spans = st.floats(min_value=0.0, max_value=0.5, allow_nan=False)


def a_queue(
    vclock: float, vmax: float, typical: float, vtime: float, answered: float | None
) -> tuple[FairQueue, Master]:
    queue = FairQueue(LineStats())
    queue.vclock, queue.vmax, queue.typical = vclock, vmax, typical
    queue.grain = typical / 2.0  # answered transactions shorter than the typical one
    master = queue.master("m")
    master.vtime, master.answered_at = vtime, answered
    return queue, master


@given(
    vclock=times,
    ahead=spans,
    typical=st.floats(min_value=0.0, max_value=0.15),  # REST_S (0.1) caps the rest
    offset=st.floats(min_value=-1.0, max_value=1.0),
    answered=st.none() | times,
    rest=st.floats(min_value=0.0, max_value=3.0),
)
def test_going_at_once_leaves_the_accounts_as_queuing_then_choosing(
    vclock: float, ahead: float, typical: float, offset: float, answered: float | None, rest: float
) -> None:
    """Every case of ``enqueue``'s rule: rested or not (answered ``rest`` typical
    transactions ago), light or not (its account behind, between or past the furthest
    account's turn and the virtual time's two typical transactions)."""
    vtime = vclock + offset
    now = (answered if answered is not None else 0.0) + rest * typical
    queued, master = a_queue(vclock, vclock + ahead, typical, vtime, answered)
    request = LineRequest(1, read(0, 10), "m", lambda _pdu, _outcome: None)
    queued.enqueue(master, request, True, now)
    chosen = queued.pop(now, lambda owner, _now: owner.queue[0] if owner.queue else None)
    assert chosen == (request, master)

    direct, same = a_queue(vclock, vclock + ahead, typical, vtime, answered)
    direct.went_at_once(same, now)

    assert (same.vtime, direct.vclock, direct.vmax) == (master.vtime, queued.vclock, queued.vmax)
    assert (queued.queued, same.queued, same.heap_seq) == (0, 0, -1) == (direct.queued, 0, -1)
