"""The reference: the Modbus TCP -> RTU forwarder a Python user would write with pymodbus.

A pymodbus ``ModbusTcpServer`` whose datastore, instead of holding values,
forwards every read and write through one ``AsyncModbusSerialClient`` (the
pattern of pymodbus's own "forwarder" example and of the ``RemoteSlaveContext``
older releases shipped). pymodbus serialises the client's transactions with
its own lock, so one request is on the line at a time; a timeout becomes
exception 0x0B and a slave's exception is passed on. It runs on the default
asyncio loop, as pymodbus's documentation and a typical user do; ``--uvloop``
runs it on uvloop like the gateway, to compare the code alone.

    python -m bench.pymodbus_forwarder --serial /dev/pts/5 --listen 127.0.0.1:5020

It logs "listening on" to stderr once it accepts connections. pymodbus is a
benchmark and test dependency only; the gateway never imports it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from collections.abc import Sequence

from pymodbus.client import AsyncModbusSerialClient
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer

log = logging.getLogger("pymodbus_forwarder")

_READS = {1, 2, 3, 4}


class ForwardingContext(ModbusServerContext):
    """A server "datastore" that answers every request by asking the RTU line."""

    def __init__(self, client: AsyncModbusSerialClient) -> None:
        # The base class builds simulated devices; a forwarder has none, so it is not
        # called. ``old_simulator`` makes the server hand requests to this object.
        self.client = client
        self.old_simulator = True
        self.simdevices = []
        self._written: dict[tuple[int, int, int], list[int] | list[bool]] = {}

    def device_ids(self) -> list[int]:
        """Broadcasts go to unit 0 on the line."""
        return [0]

    async def async_getValues(  # noqa: N802 - pymodbus names it
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        """Read through the line; after a write, pymodbus reads back what was written."""
        if func_code not in _READS:
            return self._written.pop((device_id, func_code, address), [0] * count)
        client = self.client
        try:
            if func_code == 1:
                response = await client.read_coils(address, count=count, device_id=device_id)
            elif func_code == 2:
                response = await client.read_discrete_inputs(
                    address, count=count, device_id=device_id
                )
            elif func_code == 3:
                response = await client.read_holding_registers(
                    address, count=count, device_id=device_id
                )
            else:
                response = await client.read_input_registers(
                    address, count=count, device_id=device_id
                )
        except ModbusException:
            return ExcCodes.GATEWAY_NO_RESPONSE
        if response.isError():
            return ExcCodes(response.exception_code)
        if func_code in (1, 2):
            return list(response.bits[:count])
        return list(response.registers)

    async def async_setValues(  # noqa: N802 - pymodbus names it
        self,
        device_id: int,
        func_code: int,
        address: int,
        values: Sequence[int] | Sequence[bool],
    ) -> ExcCodes | None:
        """Write through the line."""
        client = self.client
        response: ModbusPDU
        try:
            if func_code == 5:
                response = await client.write_coil(address, bool(values[0]), device_id=device_id)
            elif func_code == 15:
                response = await client.write_coils(
                    address, [bool(value) for value in values], device_id=device_id
                )
            elif func_code == 6:
                response = await client.write_register(address, int(values[0]), device_id=device_id)
            elif func_code == 16:
                response = await client.write_registers(
                    address, [int(value) for value in values], device_id=device_id
                )
            else:
                return ExcCodes.ILLEGAL_FUNCTION
        except ModbusException:
            return ExcCodes.GATEWAY_NO_RESPONSE
        if response.isError():
            return ExcCodes(response.exception_code)
        self._written[(device_id, func_code, address)] = list(values)
        return None


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host or "127.0.0.1", int(port)


async def serve(args: argparse.Namespace) -> None:
    """Open the line, then serve Modbus TCP until cancelled."""
    client = AsyncModbusSerialClient(
        args.serial,
        baudrate=args.baudrate,
        timeout=args.timeout,
        retries=args.retries,
        reconnect_delay=0.1,
    )
    if not await client.connect():
        raise OSError(f"cannot open {args.serial}")
    server = ModbusTcpServer(ForwardingContext(client), address=_host_port(args.listen))
    await server.serve_forever(background=True)
    log.warning("listening on %s", args.listen)
    try:
        await asyncio.Event().wait()
    finally:
        await server.shutdown()  # type: ignore[no-untyped-call]
        client.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: flags, logging, event loop."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--serial", required=True, help="serial device (e.g. a pty)")
    parser.add_argument("--listen", default="127.0.0.1:5020", help="HOST:PORT")
    parser.add_argument("--baudrate", type=int, default=115200)
    parser.add_argument("--timeout", type=float, default=1.0)
    parser.add_argument("--retries", type=int, default=1)
    parser.add_argument("--uvloop", action="store_true", help="run on uvloop (default: asyncio)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    try:
        if args.uvloop:
            import uvloop

            uvloop.run(serve(args))
        else:
            asyncio.run(serve(args))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
