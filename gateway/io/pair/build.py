"""A gateway's part in a redundancy pair, built from its configuration.

Imported only by a paired gateway (``Gateway.start``): a gateway alone loads none of the
pair's modules.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import TYPE_CHECKING

from ...config import GatewayConfig
from .forward import PeerForwarder
from .role import Pair

if TYPE_CHECKING:
    from ...metrics import GatewayMetrics
    from ..line.bus import Bus


def build_pair(config: GatewayConfig, buses: Mapping[str, Bus], metrics: GatewayMetrics) -> Pair:
    """One gateway of a pair: its role machine, its peer poller and its forwarder. The
    forwarder's units come from the routing table (``Pair.reroute``) once it is built."""
    redundancy = config.redundancy
    assert redundancy.peer_modbus is not None
    # Longer than the active can take: its queue's longest wait, then two attempts at most.
    waits = [line.max_queue_wait or 5.0 for line in config.lines]
    timeout = max(waits) + 2 * max(line.max_timeout for line in config.lines)
    listen = config.server.host
    local_host = None if listen in ("0.0.0.0", "::", "") else listen
    forwarder = PeerForwarder(*redundancy.peer_modbus, {}, asyncio.get_running_loop(),
                              timeout=timeout, local_host=local_host)  # fmt: skip
    return Pair(redundancy, config.metrics, buses, forwarder, metrics)
