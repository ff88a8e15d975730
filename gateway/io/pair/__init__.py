"""The redundancy pair's I/O, in one place; every decision is ``core.redundancy``'s.

* ``role``: one gateway of the pair: the role machine fed with time and evidence, obeyed.
* ``channel``: ``GET /role`` served and the peer's polled.
* ``forward``: a standby's forwarding of its masters' requests to the active.
* ``line``: a line's part in the pair.

Nothing is imported here: a gateway alone loads none of it.
"""
