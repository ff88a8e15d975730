"""The HTTP endpoint is not an open door: Host check, tokens, cookie, HTTPS and its limits.

Real clients over loopback: curl (with a cookie jar, ``--cacert``), ``http.client`` and
raw sockets, against a running gateway on a simulated line.
"""

from __future__ import annotations

import http.client
import os
import socket
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from gateway.io.http import live
from gateway.io.http.endpoint import HttpEndpoint
from gateway.io.http.live import MAX_FILTER_VALUES, LiveView
from gateway.sim import plc
from gateway.sim.pki import make_pki
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimFactory,
    require_tool,
    wait_until,
)
from tests.integration.metrics_harness import metrics_address, value

STATUS_TOKEN = "status-0123456789abcdef"
TRACE_TOKEN = "trace-0123456789abcdef"
READ_10 = bytes.fromhex("03 0000 000A")
REFUSALS = "modbus_gateway_http_refusals_total"


def gateway(make_sim: SimFactory, make_gateway: GatewayFactory, **metrics: Any) -> RunningGateway:
    sim = make_sim({1: plc(1)})
    return make_gateway({"lines": {"a": sim.line_table([1])}, "metrics": metrics})


def get(
    gw: RunningGateway, path: str, headers: dict[str, str] | None = None
) -> tuple[int, http.client.HTTPResponse, bytes]:
    """GET with ``http.client``, which sends the Host it connected to unless told another."""
    connection = http.client.HTTPConnection(*metrics_address(gw), timeout=DEADLINE_S)
    try:
        host = (headers or {}).get("Host")
        connection.putrequest("GET", path, skip_host=host is not None)
        for name, text in (headers or {}).items():
            connection.putheader(name, text)
        connection.endheaders()
        response = connection.getresponse()
        streaming = path.startswith("/trace") and response.status == 200
        return response.status, response, b"" if streaming else response.read()
    finally:
        connection.close()


def curl(*args: str) -> tuple[int, str]:
    """Run curl; the status code and the headers it received."""
    done = subprocess.run(
        [require_tool("curl"), "-s", "-o", "/dev/null", "-D", "-", "-w", "%{http_code}",
         "--max-time", str(DEADLINE_S), *args],
        capture_output=True, text=True, timeout=2 * DEADLINE_S, check=False,
    )  # fmt: skip
    return int(done.stdout[-3:]), done.stdout[:-3]


def live_view(gw: RunningGateway) -> LiveView:
    view = gw.gateway.live
    assert view is not None
    return view


def endpoint(gw: RunningGateway) -> HttpEndpoint:
    served = gw.gateway._http
    assert served is not None
    return served


def refusals(gw: RunningGateway, reason: str) -> float:
    return gw.call(lambda: value(gw, (REFUSALS, (("reason", reason),))))


def test_a_foreign_host_gets_421_on_status_and_trace_not_on_metrics(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    gw = gateway(make_sim, make_gateway, allowed_hosts=["gw.plant.example"])
    host, port = metrics_address(gw)
    base = f"http://{host}:{port}"
    for path in ("/", "/status", "/trace"):  # a page that re-bound its own name to 127.0.0.1
        code, _ = curl("-H", "Host: attacker.example:9502", base + path)
        assert code == 421, path
        code, _ = curl("-H", "Host: 127.0.0.1.nip.io", base + path)
        assert code == 421, path
    for path in ("/metrics", "/healthz", "/readyz"):  # scrapers keep working
        assert curl("-H", "Host: attacker.example", base + path)[0] == 200, path
    for name in (
        f"127.0.0.1:{port}",
        f"localhost:{port}",
        "[::1]",
        "gw.plant.example",
        "GW.Plant.Example.",
    ):
        assert curl("-H", f"Host: {name}", base + "/status")[0] == 200, name
    assert refusals(gw, "host") == 6


def test_tokens_by_header_and_by_cookie(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    gw = gateway(make_sim, make_gateway, status_token=STATUS_TOKEN, trace_token=TRACE_TOKEN)
    code, response, _ = get(gw, "/status")
    assert code == 401 and response.getheader("WWW-Authenticate", "").startswith("Bearer")
    assert get(gw, "/status", {"Authorization": "Bearer nope"})[0] == 403
    assert get(gw, "/status", {"Authorization": f"Bearer {TRACE_TOKEN}"})[0] == 403
    assert get(gw, "/status", {"Authorization": f"Bearer {STATUS_TOKEN}"})[0] == 200
    assert get(gw, "/")[0] == 401
    assert get(gw, "/trace", {"Authorization": f"Bearer {STATUS_TOKEN}"})[0] == 403
    assert get(gw, "/trace", {"Authorization": f"Bearer {TRACE_TOKEN}"})[0] == 200
    assert get(gw, "/metrics")[0] == 200  # never asks for a token
    # The browser's way: a link sets HttpOnly, SameSite=Strict cookies, sent by the page's
    # own fetch('/status') and EventSource('/trace') from then on.
    base = "http://{}:{}".format(*metrics_address(gw))
    jar = tmp_path / "cookies"
    code, head = curl("-c", str(jar), f"{base}/?token={STATUS_TOKEN}&token={TRACE_TOKEN}")
    cookies = [line for line in head.splitlines() if line.lower().startswith("set-cookie:")]
    assert code == 200 and len(cookies) == 2
    assert all("HttpOnly" in c and "SameSite=Strict" in c and "Path=/" in c for c in cookies)
    assert "referrer-policy: no-referrer" in head.lower()
    assert curl("-b", str(jar), f"{base}/status")[0] == 200
    assert curl("-b", str(jar), "-H", "Accept: text/event-stream", "--max-time", "1",
                f"{base}/trace")[0] == 200  # fmt: skip
    assert curl("-b", str(jar), f"{base}/")[0] == 200
    # The status token alone opens the page, not the trace stream.
    only_status = tmp_path / "status-only"
    assert curl("-c", str(only_status), f"{base}/?token={STATUS_TOKEN}")[0] == 200
    assert curl("-b", str(only_status), f"{base}/trace")[0] == 401
    assert curl("-b", f"mbgw_status={TRACE_TOKEN}", f"{base}/status")[0] == 403
    assert refusals(gw, "no_token") == 3 and refusals(gw, "wrong_token") == 4


def test_the_endpoint_over_https_and_with_client_certificates(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    pki = make_pki(tmp_path)
    files = {"tls_cert": str(pki.server_chain), "tls_key": str(pki.server_key)}
    gw = gateway(make_sim, make_gateway, **files)
    host, port = metrics_address(gw)
    assert curl("--cacert", str(pki.ca), f"https://localhost:{port}/metrics")[0] == 200
    assert curl("--cacert", str(pki.ca), f"https://localhost:{port}/status")[0] == 200
    assert curl(f"https://localhost:{port}/metrics")[0] == 0  # not trusted without the CA
    assert curl(f"http://{host}:{port}/metrics")[0] == 0  # no plain HTTP on an HTTPS port

    mutual = gateway(make_sim, make_gateway, tls_ca=str(pki.ca), **files)
    address = metrics_address(mutual)
    context = ssl.create_default_context(cafile=str(pki.ca))
    # No client certificate: with TLS 1.3 the refusal comes at the first read.
    with pytest.raises((ssl.SSLError, ConnectionError)):
        connection = http.client.HTTPSConnection("localhost", address[1], context=context,
                                                 timeout=DEADLINE_S)  # fmt: skip
        connection.request("GET", "/metrics")
        connection.getresponse()
    context.load_cert_chain(*pki.client("viewer"))
    connection = http.client.HTTPSConnection("localhost", address[1], context=context,
                                             timeout=DEADLINE_S)  # fmt: skip
    connection.request("GET", "/metrics")
    assert connection.getresponse().status == 200
    connection.close()


@contextmanager
def idle_from(source: str, address: tuple[str, int], count: int) -> Iterator[list[socket.socket]]:
    socks = []
    try:
        for _ in range(count):
            sock = socket.socket()
            socks.append(sock)
            sock.bind((source, 0))
            sock.settimeout(DEADLINE_S)
            sock.connect(address)
        yield socks
    finally:
        for sock in socks:
            sock.close()


def _closed(sock: socket.socket) -> bool:
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def test_one_source_holds_at_most_its_share(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    gw = gateway(make_sim, make_gateway, max_connections_per_source=2)
    address = metrics_address(gw)
    with idle_from("127.0.0.2", address, 2) as held:
        wait_until(lambda: gw.call(lambda: endpoint(gw).connections) == 2, "2 admitted")
        with idle_from("127.0.0.2", address, 1) as (third,):
            assert _closed(third)
        assert get(gw, "/healthz")[0] == 200  # another source is served
        for sock in held:  # the two let in are still open: their head may come
            sock.sendall(b"GET /healthz HTTP/1.1\r\n\r\n")
            assert sock.recv(64).startswith(b"HTTP/1.1 200")
    assert refusals(gw, "max_per_source") == 1


def test_a_trace_filter_is_bounded(make_sim: SimFactory, make_gateway: GatewayFactory) -> None:
    gw = gateway(make_sim, make_gateway)
    many = ",".join(f"10.0.{i // 250}.{i % 250}" for i in range(MAX_FILTER_VALUES + 1))
    code, _, body = get(gw, f"/trace?master={many}")
    assert code == 400 and f"at most {MAX_FILTER_VALUES}" in body.decode()
    code, _, body = get(gw, f"/trace?unit=1&master={many.partition(',')[2]}")
    assert code == 400, "the bound counts every parameter together"
    fits = ",".join(many.split(",")[:MAX_FILTER_VALUES])
    assert get(gw, f"/trace?master={fits}")[0] == 200


def test_a_stream_that_reads_nothing_is_closed_and_counted(
    make_sim: SimFactory, make_gateway: GatewayFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(live, "STALL_S", 0.5)
    gw = gateway(make_sim, make_gateway)
    stalled = ("modbus_gateway_trace_streams_closed_total", (("reason", "stalled"),))
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.settimeout(DEADLINE_S)
    sock.connect(metrics_address(gw))
    sock.sendall(b"GET /trace HTTP/1.1\r\nHost: localhost\r\n\r\n")  # and never reads
    wait_until(lambda: gw.call(lambda: len(live_view(gw).hub.streams)) == 1, "the stream")
    with gw.connect() as master:
        deadline_rounds = 4000
        while gw.call(lambda: value(gw, stalled)) == 0:
            deadline_rounds -= 1
            assert deadline_rounds > 0, "the stream was never closed"
            for _ in range(8):
                master.send(1, READ_10)
            for _ in range(8):
                assert master.receive().pdu[:2] == b"\x03\x14"
    assert gw.call(lambda: len(live_view(gw).hub.streams)) == 0
    sock.close()
    assert get(gw, "/trace")[0] == 200  # the slot is free again


def test_connections_open_is_per_listener(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "lines": {"a": sim.line_table([1])},
        "listeners": [{"name": "second", "protocol": "tcp", "listen": "127.0.0.1:0"}],
    })  # fmt: skip
    second = gw.call(lambda: gw.gateway.listener_address("second"))
    gauge = "modbus_gateway_connections_open"
    with gw.connect() as one, gw.connect() as two, socket.create_connection(second) as three:
        assert one.request(1, READ_10)[0] == 3 and two.request(1, READ_10)[0] == 3
        three.sendall(bytes.fromhex("0001 0000 0006 01") + READ_10)
        assert three.recv(256)
        assert gw.call(lambda: value(gw, (gauge, (("listener", "tcp"),)))) == 2
        assert gw.call(lambda: value(gw, (gauge, (("listener", "second"),)))) == 1
    wait_until(lambda: gw.call(lambda: value(gw, (gauge, (("listener", "tcp"),)))) == 0, "closed")


def test_status_pollers_share_renderings(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    gw = gateway(make_sim, make_gateway)
    renderer = live_view(gw).status_renderer
    answered: list[int] = []

    def poll() -> None:
        for _ in range(25):
            answered.append(get(gw, "/status")[0])

    pollers = [threading.Thread(target=poll) for _ in range(4)]
    for poller in pollers:
        poller.start()
    for poller in pollers:
        poller.join(DEADLINE_S * 3)
    assert answered.count(200) == 100
    assert gw.call(lambda: renderer.renderings) < 100  # shared and spaced, not one each


def test_the_trace_client_over_https_with_its_token(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    pki = make_pki(tmp_path)
    gw = gateway(make_sim, make_gateway, tls_cert=str(pki.server_chain),
                 tls_key=str(pki.server_key), trace_token=TRACE_TOKEN)  # fmt: skip
    url = f"https://localhost:{metrics_address(gw)[1]}"
    command = [sys.executable, "-m", "gateway", "trace", "--url", url, "--cacert", str(pki.ca),
               "--json", "--count", "1"]  # fmt: skip
    refused = subprocess.run(command, capture_output=True, text=True, timeout=2 * DEADLINE_S,
                             check=False)  # fmt: skip
    assert refused.returncode == 2 and "answered 401" in refused.stderr
    env = dict(os.environ, MODBUS_GATEWAY_TRACE_TOKEN=TRACE_TOKEN)
    with subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as client:  # fmt: skip
        assert client.stderr is not None and client.stdout is not None
        assert client.stderr.readline().startswith("tracing ")  # the stream is open
        with gw.connect() as master:
            assert master.request(1, READ_10)[0] == 3
        out, _ = client.communicate(timeout=2 * DEADLINE_S)
    assert client.returncode == 0 and '"type":"request"' in out.replace(" ", "")


def test_https_handshakes_count_against_the_caps(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    pki = make_pki(tmp_path)
    gw = gateway(make_sim, make_gateway, tls_cert=str(pki.server_chain),
                 tls_key=str(pki.server_key), max_connections_per_source=2,
                 header_timeout=0.5)  # fmt: skip
    address = metrics_address(gw)
    with idle_from("127.0.0.2", address, 2) as silent:  # connected, never a ClientHello
        wait_until(lambda: gw.call(lambda: endpoint(gw).connections) == 2, "2 admitted")
        with idle_from("127.0.0.2", address, 1) as (third,):
            assert _closed(third)  # at once: the source holds its share in handshakes
        assert all(_closed(sock) for sock in silent)  # the handshake timeout (0.5 s)
    wait_until(lambda: gw.call(lambda: endpoint(gw).connections) == 0, "handshakes freed")
    assert refusals(gw, "max_per_source") == 1
    context = ssl.create_default_context(cafile=str(pki.ca))
    connection = http.client.HTTPSConnection("localhost", address[1], context=context,
                                             timeout=DEADLINE_S)  # fmt: skip
    connection.request("GET", "/healthz")
    assert connection.getresponse().status == 200
    connection.close()
