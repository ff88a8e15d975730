"""The ``rtu-over-tcp`` listener: masters that send RTU frames over TCP (SCADA, HMIs).

Theory of operation: the same server as Modbus TCP (allow lists, the same
request admission from ``core.admission``, metrics, trace), with RTU framing on each
connection: requests are split by predicted length and CRC
(``core.rtu_stream.RtuStreamDecoder``), a request of unknown length ends after
``SILENCE_S`` of quiet, and replies are RTU frames. RTU has no transaction id,
so a connection has one request at a time (``max_pipeline`` is 1 here): the
next request is read only once the previous one is answered, which keeps the
answers in the order of the requests. A broadcast (unit 0) is never answered,
as on a serial line; a bad CRC closes the connection (the stream cannot be
resynchronised with certainty) and is counted in ``protocol_errors_total``.
"""

from __future__ import annotations

import asyncio
import ssl

from ...config import ListenerConfig, ServerConfig
from ...core.outcome import Outcome
from ...core.policy import IPAddress, Policy
from ...core.rtu_stream import RtuStreamDecoder, encode_rtu_reply
from ...metrics import GatewayMetrics
from .spine import Router
from .tcp import MasterConnection, ModbusTcpServer

#: Quiet time that ends a request whose length its function code does not tell.
SILENCE_S = 0.05


class RtuMasterConnection(MasterConnection):
    """One master speaking RTU over TCP; answered in order, one request at a time."""

    def __init__(
        self,
        server: ModbusTcpServer,
        peer: str,
        source: str,
        accepted: float,
        address: IPAddress | None = None,
    ) -> None:
        self._rtu = RtuStreamDecoder()
        super().__init__(server, peer, source, accepted, address, self._rtu)
        self._silence_timer: asyncio.TimerHandle | None = None

    def buffer_updated(self, nbytes: int) -> None:
        super().buffer_updated(nbytes)
        self._arm_silence()

    def _arm_silence(self) -> None:
        if self._silence_timer is not None:
            self._silence_timer.cancel()
            self._silence_timer = None
        if self._rtu.awaiting_silence and not self._closed:
            loop = asyncio.get_running_loop()
            self._silence_timer = loop.call_later(SILENCE_S, self._silence_over)

    def _silence_over(self) -> None:
        self._silence_timer = None
        self._rtu.silence()
        self._run_batch()

    def _send(
        self, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        if unit == 0:
            return  # a broadcast is never answered on RTU
        if self._transport is None or self._closed:
            return
        frame = encode_rtu_reply(unit, pdu)
        if self._batch is not None:
            self._batch.append(frame)
        else:
            self._transport.write(frame)
        tracer = self._server.tracer
        if tracer.active:
            tracer.reply(self.peer, transaction_id, unit, pdu, outcome)

    def _release(self) -> None:
        if self._silence_timer is not None:
            self._silence_timer.cancel()
            self._silence_timer = None
        super()._release()


def rtu_over_tcp_server(
    config: ServerConfig,
    router: Router,
    metrics: GatewayMetrics,
    listener: ListenerConfig | None = None,
    policy: Policy | None = None,
    ssl_context: ssl.SSLContext | None = None,
) -> ModbusTcpServer:
    """A listener for RTU-over-TCP masters: one request in flight each, no broadcast replies."""
    return ModbusTcpServer(
        config,
        router,
        metrics,
        listener,
        policy,
        ssl_context,
        connection_class=RtuMasterConnection,
        one_at_a_time=True,
    )
