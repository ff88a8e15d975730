"""Who may read the HTTP endpoint's status page, ``/status`` and ``/trace``.

Theory of operation: ``/metrics``, ``/healthz`` and ``/readyz`` are ``RouteAccess.OPEN``
(scrapers and health checks reach them whatever they send). The other routes are
guarded, in this order:

1. **Host.** A browser sends the name it resolved in ``Host``; a web page that
   re-binds its own name to 127.0.0.1 (DNS rebinding) still sends its own name. Only
   loopback names, the endpoint's listen address, the address the connection came
   in on and ``metrics.allowed_hosts`` are answered; any other gets 421. A request
   without a ``Host`` (no browser sends one) passes.
2. **Token** (when configured for the route's access): ``Authorization: Bearer``
   (scripts), the cookie a ``?token=`` link set (the page: an ``EventSource`` cannot
   send headers), or that ``?token=`` itself, which then sets the cookie
   (``HttpOnly``, ``SameSite=Strict``) for every access whose token it is. Nothing
   presented is 401; a wrong token is 403. Tokens are compared in constant time.
"""

from __future__ import annotations

import enum
import hmac
from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import parse_qs

from ...config import MetricsConfig, is_loopback


class RouteAccess(enum.Enum):
    """What a route exposes, hence what guards it."""

    OPEN = "open"  #: metrics and health: any Host, no token
    STATUS = "status"  #: the page and /status: Host check, status_token
    TRACE = "trace"  #: /trace (register values): Host check, trace_token


class HttpRefusal(enum.StrEnum):
    """Why the endpoint turned a connection or a request away (a metric's label)."""

    HOST = "host"  #: 421: a Host the endpoint does not answer for
    NO_TOKEN = "no_token"  #: 401: a token is needed and none came
    WRONG_TOKEN = "wrong_token"  #: 403: the token that came is not the one
    MAX_PER_SOURCE = "max_per_source"  #: closed at accept: the source holds its share
    MAX_CONNECTIONS = "max_connections"  #: closed at accept: every connection is busy


_COOKIE = {RouteAccess.STATUS: "mbgw_status", RouteAccess.TRACE: "mbgw_trace"}
_STATUS: dict[HttpRefusal | None, int] = {HttpRefusal.HOST: 421, HttpRefusal.NO_TOKEN: 401}


@dataclass(frozen=True, slots=True)
class Verdict:
    """A guard's answer: ``refusal`` ``None`` lets the request through."""

    refusal: HttpRefusal | None = None
    set_cookies: tuple[str, ...] = ()

    @property
    def status(self) -> int:
        """The HTTP status of a refusal."""
        return _STATUS.get(self.refusal, 403)

    @property
    def challenge(self) -> str:
        """The header line a 401 carries (RFC 6750), else nothing."""
        if self.refusal is HttpRefusal.NO_TOKEN:
            return 'WWW-Authenticate: Bearer realm="modbus-gateway"\r\n'
        return ""

    @property
    def message(self) -> bytes:
        """The body of a refusal: what to do about it."""
        if self.refusal is HttpRefusal.HOST:
            return (
                b"misdirected request: this endpoint does not answer for that Host; "
                b"add the name to metrics.allowed_hosts\n"
            )
        if self.refusal is HttpRefusal.NO_TOKEN:
            return b"a token is needed: Authorization: Bearer TOKEN, or open /?token=TOKEN\n"
        return b"wrong token\n"


def host_name(header: str) -> str:
    """The name in a ``Host`` header: lower case, without port, brackets or final dot."""
    host = header.strip().lower()
    if host.startswith("["):
        return host[1:].partition("]")[0]
    if host.count(":") == 1:
        host = host.partition(":")[0]
    return host.rstrip(".")


def _cookies(header: str) -> dict[str, str]:
    pairs = (part.strip().partition("=") for part in header.split(";"))
    return {name.strip(): value.strip() for name, _, value in pairs if name.strip()}


def _same(given: str, token: str) -> bool:
    return hmac.compare_digest(given.encode(), token.encode())


class Guard:
    """The Host check and the tokens of one endpoint (module docstring)."""

    def __init__(self, config: MetricsConfig) -> None:
        listen = host_name(config.host)
        self._hosts = frozenset({listen, *config.allowed_hosts}) - {"0.0.0.0", "::", ""}
        self._tokens = {
            RouteAccess.STATUS: config.status_token,
            RouteAccess.TRACE: config.trace_token,
        }
        self._secure = config.tls_cert is not None

    def host_allowed(self, header: str | None, local_address: str) -> bool:
        """True when a browser that sent ``header`` is talking to this endpoint by name."""
        if header is None:
            return True
        name = host_name(header)
        return name in self._hosts or is_loopback(name) or name == local_address.lower()

    def judge(
        self, access: RouteAccess, target: str, headers: Mapping[str, str], local_address: str
    ) -> Verdict:
        """Whether the request may have the route, and the cookies a ``?token=`` sets."""
        if access is RouteAccess.OPEN:
            return Verdict()
        if not self.host_allowed(headers.get("host"), local_address):
            return Verdict(HttpRefusal.HOST)
        offered = parse_qs(target.partition("?")[2]).get("token", [])
        cookies = tuple(
            self._cookie(kind, token)
            for kind, token in self._tokens.items()
            if token is not None and any(_same(given, token) for given in offered)
        )
        token = self._tokens[access]
        if token is None:
            return Verdict(None, cookies)
        scheme, _, bearer = headers.get("authorization", "").partition(" ")
        given = [*offered, _cookies(headers.get("cookie", "")).get(_COOKIE[access], "")]
        if scheme.lower() == "bearer":
            given.append(bearer.strip())
        given = [value for value in given if value]
        if any([_same(value, token) for value in given]):  # each compared, in constant time
            return Verdict(None, cookies)
        return Verdict(HttpRefusal.WRONG_TOKEN if given else HttpRefusal.NO_TOKEN)

    def _cookie(self, access: RouteAccess, token: str) -> str:
        secure = "; Secure" if self._secure else ""
        return f"{_COOKIE[access]}={token}; Path=/; HttpOnly; SameSite=Strict{secure}"
