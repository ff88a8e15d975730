"""pymodbus servers as independent slaves, each serving on an event loop of its own."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

from tests.helpers import DEADLINE_S


def sim_device(unit: int, coils: list[bool], holding: list[int]) -> Any:
    """A pymodbus simulated device: ``coils`` and ``holding`` from address 0, 16 of the rest."""
    from pymodbus.simulator import DataType, SimData, SimDevice

    return SimDevice(
        id=unit,
        simdata=(
            [SimData(0, values=coils, datatype=DataType.BITS)],
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, values=holding, datatype=DataType.REGISTERS)],
            [SimData(0, count=16, values=0, datatype=DataType.REGISTERS)],
        ),
    )


class PymodbusServerThread:
    """``make()`` builds a pymodbus server on the thread's loop (pymodbus binds its
    transport to the running loop when a server is constructed), which then serves."""

    def __init__(self, make: Callable[[], Any], name: str) -> None:
        self.loop = asyncio.new_event_loop()
        self.server: Any = None
        ready = threading.Event()

        async def start() -> None:
            self.server = make()
            await self.server.serve_forever(background=True)

        def serve() -> None:
            asyncio.set_event_loop(self.loop)
            self.loop.run_until_complete(start())
            ready.set()
            self.loop.run_forever()

        self._thread = threading.Thread(target=serve, name=name, daemon=True)
        self._thread.start()
        assert ready.wait(DEADLINE_S), f"{name} did not start serving"

    @property
    def port(self) -> int:
        """The TCP port a network server bound (port 0 asked)."""
        port: int = self.server.transport.sockets[0].getsockname()[1]
        return port

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(DEADLINE_S)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(DEADLINE_S)
        self.loop.close()
