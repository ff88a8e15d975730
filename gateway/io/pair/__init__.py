"""The redundancy pair's I/O, in one place; every decision is ``core.redundancy``'s.

* ``build``: a gateway's part in the pair, built from its configuration.
* ``role``: one gateway of the pair: the role machine fed with time and evidence, obeyed.
* ``channel``: ``GET /role`` served, and the peer's polled.
* ``forward``: a standby's forwarding of its masters' requests to the active.
* ``line``: a line's part in the pair: the role its driver holds (``io.bus.LineRole``).

The line driver (``io.bus``) imports nothing from here; this package imports the driver.
Nothing is imported here either: a gateway alone loads none of it.
"""
