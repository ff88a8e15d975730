"""``modbus-gateway trace --url http://HOST:PORT``: watch a running gateway's traffic.

Attaches to the gateway's ``GET /trace`` stream (newline-delimited JSON), so
nothing is restarted and no serial port or TCP port is taken. Prints one line
per frame (or the JSON itself with ``--json``) and, with ``--pcap FILE``,
writes a pcapng capture Wireshark opens as it is (see ``gateway.pcap``).
Filters are applied by the gateway, so a busy gateway sends only what is asked.
An ``https://`` URL is checked against ``--cacert`` (else the system's CAs); the
endpoint's ``trace_token`` is read from ``MODBUS_GATEWAY_TRACE_TOKEN`` (an
environment variable, so that it does not show in the process list).
"""

from __future__ import annotations

import argparse
import http.client
import ipaddress
import json
import os
import signal
import socket
import ssl
import sys
import time
from collections.abc import Sequence
from types import FrameType
from typing import Any
from urllib.parse import urlencode, urlsplit

from .io.frame_trace import parse_function
from .pcap import IpAddress, PcapngWriter


def _function_code(text: str) -> str:
    try:
        return str(parse_function(text))
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    """The ``modbus-gateway trace --url`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="modbus-gateway trace",
        description="Attach to a running gateway's live trace (its HTTP endpoint). Without "
        "--url, 'trace' runs a gateway with the trace logged instead (see modbus-gateway -h).",
    )
    parser.add_argument(
        "--url",
        required=True,
        metavar="http://HOST:PORT",
        help="the gateway's HTTP endpoint ([metrics] listen; https:// when it "
        "has tls_cert); its trace_token, if any, in "
        "MODBUS_GATEWAY_TRACE_TOKEN",
    )
    parser.add_argument(
        "--cacert",
        metavar="FILE",
        help="CA certificates an https:// endpoint's certificate chains to",
    )
    parser.add_argument("--line", action="append", default=[], help="only this line (repeatable)")
    parser.add_argument(
        "--unit",
        action="append",
        type=int,
        default=[],
        metavar="N",
        help="only TCP unit id N (repeatable)",
    )
    parser.add_argument(
        "--function",
        action="append",
        type=_function_code,
        default=[],
        metavar="FC",
        help="only function FC: 3, 0x10 or read_holding_registers (repeatable)",
    )
    parser.add_argument(
        "--outcome",
        action="append",
        default=[],
        help="only replies with this outcome: ok, target_failed, no_route, ... (repeatable)",
    )
    parser.add_argument(
        "--master",
        action="append",
        default=[],
        metavar="HOST[:PORT]",
        help="only this master (repeatable)",
    )
    parser.add_argument(
        "--pcap", metavar="FILE", help="also write a pcapng capture (Modbus/TCP and Modbus RTU)"
    )
    parser.add_argument("--json", action="store_true", help="print the events as JSON lines")
    parser.add_argument("--count", type=int, metavar="N", help="stop after N events")
    parser.add_argument(
        "--connect-timeout", type=float, default=5.0, metavar="SECONDS", help=argparse.SUPPRESS
    )
    return parser


def format_event(event: dict[str, Any]) -> str:
    """One human-readable line per event."""
    if event.get("type") == "gap":
        return f"... {event['dropped']} event(s) dropped: this client read too slowly"
    clock = time.strftime("%H:%M:%S", time.localtime(event["time"]))
    millis = int((event["time"] % 1) * 1000)
    arrow = {"request": "->", "reply": "<-"}.get(event["type"], "x ")
    where = ""
    if event.get("line") is not None:
        where = f" [line {event['line']} slave {event['slave']}]"
    text = (
        f"{clock}.{millis:03d} {arrow} {event['master']} tid={event['tid']} "
        f"unit={event['unit']}{where} {event['function']}({event['fc']}) {event.get('detail', '')}"
    )
    if event.get("outcome"):
        text += f" {event['outcome']}"
    if event.get("latency_ms") is not None:
        text += f" {event['latency_ms']:.2f} ms"
    if event["type"] == "request":
        text += f"  [{event['hex']}]"
    return text


def _gateway_address(host: str) -> IpAddress:
    """The gateway's IP for the capture: the URL's host, resolved when it is a name."""
    try:
        return ipaddress.ip_address(host)
    except ValueError:
        try:
            return ipaddress.ip_address(socket.gethostbyname(host))
        except (OSError, ValueError):
            return ipaddress.IPv4Address("127.0.0.1")


class TraceCapture:
    """Turns trace events into capture frames: TCP at once, the line's once the outcome is known.

    A request reaches the line only if its reply says so (an answer from the slave or its
    silence); requests answered by the gateway itself (rejected, no route, cached) are not
    put on the line side.
    """

    #: Outcomes whose request was sent on the line, and those whose answer came from it.
    SENT = frozenset({"ok", "slave_exception", "target_failed"})
    ANSWERED = frozenset({"ok", "slave_exception"})
    MAX_PENDING = 4096

    def __init__(self, writer: PcapngWriter) -> None:
        self.writer = writer
        self._pending: dict[tuple[str, int, int], dict[str, Any]] = {}

    def add(self, event: dict[str, Any]) -> None:
        """Put one trace event in the capture."""
        kind = event.get("type")
        if kind not in ("request", "reply"):
            return
        pdu = bytes.fromhex(event["hex"])
        key = (event["master"], event["tid"], event["unit"])
        if kind == "request":
            self.writer.tcp(event["time"], event["master"], True, event["tid"], event["unit"], pdu)
            if event.get("line") is not None:
                if len(self._pending) >= self.MAX_PENDING:
                    del self._pending[next(iter(self._pending))]
                self._pending[key] = event
            return
        if pdu:  # a broadcast without a reply has nothing on the TCP side
            self.writer.tcp(event["time"], event["master"], False, event["tid"], event["unit"], pdu)
        request = self._pending.pop(key, None)
        outcome = event.get("outcome")
        if request is None or outcome not in self.SENT:
            return
        line, slave = request["line"], request["slave"]
        self.writer.rtu(request["time"], line, True, slave, bytes.fromhex(request["hex"]))
        if outcome in self.ANSWERED:
            self.writer.rtu(event["time"], line, False, slave, pdu)


def _trace_path(base: str, args: argparse.Namespace) -> str:
    """``/trace`` under the URL's path, with the filters as its query."""
    query = [("line", v) for v in args.line] + [("unit", str(v)) for v in args.unit]
    query += [("function", v) for v in args.function] + [("outcome", v) for v in args.outcome]
    query += [("master", v) for v in args.master]
    return (base.rstrip("/") or "") + "/trace" + ("?" + urlencode(query) if query else "")


def _connection(
    scheme: str, host: str, port: int | None, args: argparse.Namespace
) -> http.client.HTTPConnection:
    """An HTTP or HTTPS connection to the endpoint (not opened yet)."""
    if scheme == "https":
        context = ssl.create_default_context(cafile=args.cacert)
        return http.client.HTTPSConnection(
            host, port or 443, timeout=args.connect_timeout, context=context
        )
    return http.client.HTTPConnection(host, port or 80, timeout=args.connect_timeout)


def _headers() -> dict[str, str]:
    """The request's headers: the trace token from the environment, when given."""
    headers = {"Accept": "application/x-ndjson"}
    token = os.environ.get("MODBUS_GATEWAY_TRACE_TOKEN")
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers


_STOP_SIGNALS = {signal.SIGTERM, signal.SIGINT}


class _StopRequestedError(Exception):
    """SIGTERM or SIGINT: finish the capture and exit 0."""


def _on_signal(_signum: int, _frame: FrameType | None) -> None:
    raise _StopRequestedError


def _follow(
    response: http.client.HTTPResponse, args: argparse.Namespace, capture: TraceCapture | None
) -> int:
    """Print (and capture) events until ``--count`` is reached (0) or the stream ends (1)."""
    seen = 0
    while args.count is None or seen < args.count:
        raw = response.readline()
        if not raw:
            print("modbus-gateway trace: the gateway closed the stream", file=sys.stderr)
            return 1
        if not raw.strip():
            continue
        event = json.loads(raw)
        if event.get("type") == "heartbeat":
            continue
        # A stop signal lands between events, never inside a capture block.
        signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
        seen += 1
        if capture is not None:
            capture.add(event)
        print(json.dumps(event) if args.json else format_event(event), flush=True)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    return 0


def main(argv: Sequence[str]) -> int:
    """Run the client; 0 on a clean stop, 1 when the gateway went away, 2 on bad input."""
    args = build_parser().parse_args(argv)
    url = urlsplit(args.url)
    if url.scheme not in ("http", "https") or not url.hostname:
        print(
            f"modbus-gateway trace: --url {args.url!r}: expected http://HOST:PORT or https://HOST:PORT",
            file=sys.stderr,
        )
        return 2
    path = _trace_path(url.path, args)
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    connection = _connection(url.scheme, url.hostname, url.port, args)
    pcap_file = None
    try:
        try:
            connection.request("GET", path, headers=_headers())
            response = connection.getresponse()
        except OSError as error:
            print(
                f"modbus-gateway trace: cannot reach {args.url}: {error}; is the gateway "
                "running with its HTTP endpoint ([metrics] listen) there?",
                file=sys.stderr,
            )
            return 1
        if response.status != 200:
            body = response.read().decode(errors="replace").strip()
            print(
                f"modbus-gateway trace: {args.url} answered {response.status}: {body}",
                file=sys.stderr,
            )
            return 2
        if connection.sock is not None:
            connection.sock.settimeout(None)  # a quiet line may send nothing for hours
        capture = None
        if args.pcap:
            pcap_file = open(args.pcap, "wb")  # noqa: SIM115 - closed in the finally below
            capture = TraceCapture(PcapngWriter(pcap_file, _gateway_address(url.hostname)))
        print(f"tracing {args.url} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        return _follow(response, args, capture)
    except _StopRequestedError:
        pass
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        connection.close()
        if pcap_file is not None:
            pcap_file.close()
            print(
                f"wrote {args.pcap}: open it with wireshark or 'tshark -r {args.pcap}'",
                file=sys.stderr,
            )
    return 0
