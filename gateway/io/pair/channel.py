"""The pair's network channel: ``GET /role`` served, and the peer's ``/role`` polled.

Theory of operation. Each gateway of a pair answers ``GET /role`` on its HTTP endpoint
with its role, what remains of its lease and its priority, as JSON: 200 while active,
503 while standby, so a keepalived check script (``curl -sf``) follows the active. The
other gateway polls it every quarter lease over a fresh connection, with the endpoint's
token (``status_token``) and over HTTPS when the endpoint serves HTTPS. A poll that does
not answer within half a lease, answers garbage or is refused is *unreachable*: evidence
of nothing but a lost channel (the bus decides then; ``core.redundancy``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import ssl
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from ...core.redundancy import Role

log = logging.getLogger("gateway.pair")

#: The largest ``/role`` answer read: a few fields of JSON.
MAX_ROLE_ANSWER = 4096


@dataclass(frozen=True, slots=True)
class PeerRole:
    """What the peer's ``/role`` said, and when it was asked (the poller's clock)."""

    role: Role
    lease_remaining: float
    priority: int
    peer_lease_remaining: float = 0.0
    asked_at: float | None = None


def role_body(
    role: Role, lease_remaining: float, priority: int, paired: bool,
    peer_lease_remaining: float = 0.0,
) -> bytes:  # fmt: skip
    """The JSON of ``/role`` (see ``core.redundancy.RoleReport`` for the two leases)."""
    document = {
        "role": role.value,
        "lease_remaining": round(max(0.0, lease_remaining), 3),
        "priority": priority,
        "paired": paired,
        # Rounded down: the peer reads it as how long it may still count on this gateway.
        "peer_lease_remaining": max(0.0, int(peer_lease_remaining * 1000) / 1000),
    }
    return (json.dumps(document) + "\n").encode()


def alone_role_body(priority: int) -> tuple[int, bytes]:
    """``/role`` of a gateway without a peer: 200, active, nothing claimed, not paired."""
    return 200, role_body(Role.ACTIVE, 0.0, priority, False)


def parse_role(status: int, body: bytes) -> PeerRole:
    """The peer's answer; ``ValueError`` for anything but a ``/role`` document."""
    if status not in (200, 503):
        raise ValueError(f"HTTP {status}")
    document = json.loads(body)
    if not isinstance(document, dict):
        raise ValueError("not a JSON object")
    role = Role(document["role"])
    lease = document["lease_remaining"]
    priority = document["priority"]
    if not isinstance(lease, int | float) or isinstance(lease, bool) or lease < 0:
        raise ValueError("lease_remaining is not a number of seconds")
    if not isinstance(priority, int) or isinstance(priority, bool):
        raise ValueError("priority is not an integer")
    acknowledged = document.get("peer_lease_remaining", 0.0)
    if not isinstance(acknowledged, int | float) or isinstance(acknowledged, bool):
        raise ValueError("peer_lease_remaining is not a number of seconds")
    return PeerRole(role, float(lease), priority, max(0.0, float(acknowledged)))


def split_answer(answer: bytes) -> tuple[int, Mapping[str, str], bytes]:
    """Status, headers and body of an HTTP/1.1 answer read to its end."""
    head, separator, body = answer.partition(b"\r\n\r\n")
    if not separator:
        raise ValueError("no end of the answer's head")
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ", 2)
    if len(parts) < 2 or not parts[0].startswith("HTTP/1.") or not parts[1].isdigit():
        raise ValueError("not an HTTP answer")
    headers = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    return int(parts[1]), headers, body


class PeerPoller:
    """Polls the peer's ``/role``; each result goes to ``on_role`` or ``on_unreachable``."""

    def __init__(
        self,
        address: tuple[str, int],
        *,
        interval: float,
        timeout: float,
        on_role: Callable[[PeerRole], None],
        on_unreachable: Callable[[str], None],
        token: str | None = None,
        tls: ssl.SSLContext | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.address = address
        self._clock = clock
        self.interval = interval
        self.timeout = timeout
        self._on_role = on_role
        self._on_unreachable = on_unreachable
        self._token = token
        self._tls = tls
        self._task: asyncio.Task[None] | None = None
        self._why = ""  # the last reason logged: logged again only when it changes

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="peer-role")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _run(self) -> None:
        while True:
            try:
                peer = await asyncio.wait_for(self.poll(), self.timeout)
            except (OSError, ValueError, KeyError, TimeoutError, ssl.SSLError) as error:
                why = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
                if why != self._why:
                    log.warning("pair: peer %s:%d unreachable (%s)", *self.address, why)
                    self._why = why
                self._on_unreachable(why)
            else:
                if self._why:
                    log.info("pair: peer %s:%d answers again", *self.address)
                    self._why = ""
                self._on_role(peer)
            await asyncio.sleep(self.interval)

    async def poll(self) -> PeerRole:
        """One ``GET /role``, stamped with when it was asked (on ``clock``)."""
        asked_at = None if self._clock is None else self._clock()
        host, port = self.address
        reader, writer = await asyncio.open_connection(
            host, port, ssl=self._tls, server_hostname=host if self._tls else None
        )
        try:
            head = f"GET /role HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n"
            if self._token:
                head += f"Authorization: Bearer {self._token}\r\n"
            writer.write((head + "\r\n").encode())
            answer = await reader.read(MAX_ROLE_ANSWER + 1)
            while len(answer) <= MAX_ROLE_ANSWER:
                more = await reader.read(MAX_ROLE_ANSWER + 1 - len(answer))
                if not more:
                    break
                answer += more
            if len(answer) > MAX_ROLE_ANSWER:
                raise ValueError("an answer longer than a /role document")
        finally:
            writer.close()
            with contextlib.suppress(OSError, ssl.SSLError):
                await writer.wait_closed()
        status, _headers, body = split_answer(answer)
        return replace(parse_role(status, body), asked_at=asked_at)


def peer_tls(cert: str | None, key: str | None, ca: str | None) -> ssl.SSLContext | None:
    """The client context for an HTTPS peer (``None`` when the endpoint serves plain HTTP):
    the peer's certificate is checked against ``ca`` (the endpoint's ``tls_ca``, else the
    system's) and must name the address ``peer`` gives (an IP address entry for an IP), as
    a TLS slave's must: any other certificate of the plant's CA is not the peer. This
    gateway's own endpoint certificate is offered for a peer that asks."""
    if cert is None:
        return None
    context = ssl.create_default_context(cafile=ca)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    if key is not None:
        context.load_cert_chain(cert, key)
    return context
