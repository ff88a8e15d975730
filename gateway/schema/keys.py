"""Every key of the configuration file, declared once (see ``gateway.schema``).

The order here is the order of the example configuration and of the reference page.
"""

from __future__ import annotations

from ..core.line import MAX_IN_FLIGHT
from .model import Flag, Key, Reload, Scope, Show, Table, Type

_S, _LS, _M, _LG = Table.SERVER, Table.LISTENERS, Table.METRICS, Table.LOGGING
_A, _PAIR = Table.AUDIT, Table.REDUNDANCY
_L, _C, _RT, _P, _R = Table.LINES, Table.CACHE, Table.ROUTES, Table.POLICIES, Table.RULES
_LINE_KINDS = ("rtu", "ascii", "rtu-over-tcp", "tcp", "tls")
_NETWORK = 'kind = "rtu-over-tcp", "tcp" or "tls"'
_SERIAL = 'kind = "rtu" or "ascii"'
_TLS = 'kind = "tls"'
_SLAVE = 'protocol = "serial-slave"'

SERVER = (
    Key(
        table=_S,
        name="listen",
        type=Type.ADDRESS,
        default="0.0.0.0:502",
        reload=Reload.RESTART,
        help="Modbus TCP address to listen on (502 needs root or CAP_NET_BIND_SERVICE): the "
        'listener named "tcp". Without it, that listener exists only when no other network '
        "listener is configured.",
        flag=Flag(
            name="--listen",
            metavar="HOST:PORT",
            help="Modbus TCP address (default 0.0.0.0:502; 127.0.0.1:5020 with --demo)",
        ),
    ),
    Key(
        table=_S,
        name="max_connections",
        type=Type.INTEGER,
        default=100,
        low=1,
        high=100_000,
        help="Masters connected at once, on every listener together; at the cap, when_full "
        "says what happens.",
    ),
    Key(
        table=_S,
        name="when_full",
        type=Type.CHOICE,
        default="close_oldest_idle",
        choices=("close_oldest_idle", "refuse"),
        help="At max_connections, under either choice, a newcomer from an address holding "
        "less than its fair share (max_connections / addresses) takes the place of the "
        "longest-open connection that never sent a request of the address holding the most; "
        "no connection that has sent a request is closed while one that never did is open. "
        'Otherwise "close_oldest_idle" closes the master that has been idle longest (the TCP '
        'implementation guide\'s advice, shared out by address), "refuse" turns the new one '
        "away.",
    ),
    Key(
        table=_S,
        name="evict_min_idle",
        type=Type.SECONDS,
        default=10.0,
        low=0.0,
        high=86_400.0,
        help="Only a master idle (no request in flight, none received) for at least this "
        "many seconds may be closed to make room for a newcomer of its own address (or one a "
        "connection lighter); when there is none, the new connection is refused. A "
        "connection that never sent a request, taken for a lighter address, need not wait.",
    ),
    Key(
        table=_S,
        name="max_connections_per_source",
        type=Type.INTEGER,
        default=0,
        low=0,
        high=100_000,
        help="Connections from one source address at once (0 = no cap); more are refused "
        "at accept. Without a cap, at max_connections the address holding the most "
        "connections yields its longest-idle one (docs/listeners-and-security.md, "
        '"Hostile masters and networks").',
    ),
    Key(
        table=_S,
        name="idle_timeout",
        type=Type.SECONDS,
        default=300.0,
        low=0.0,
        high=86_400.0,
        help="Seconds without a complete request after which a master with nothing in flight "
        "is disconnected (0 = never). Stray bytes that do not complete a request do not "
        "count.",
    ),
    Key(
        table=_S,
        name="send_timeout",
        type=Type.SECONDS,
        default=10.0,
        low=0.0,
        high=3600.0,
        help="Seconds a master may leave its replies unread (the gateway's send buffer stays "
        "full) before it is disconnected (0 = never).",
    ),
    Key(
        table=_S,
        name="max_pipeline",
        type=Type.INTEGER,
        default=16,
        low=1,
        high=256,
        help="Requests one master may have in flight (pipelining); past this the gateway "
        "stops reading from that connection until a reply goes out.",
    ),
    Key(
        table=_S,
        name="backlog",
        type=Type.INTEGER,
        default=1024,
        low=1,
        high=65_535,
        reload=Reload.RESTART,
        help="Listen backlog: pending connections the kernel queues before accept (capped "
        "by net.core.somaxconn).",
    ),
    Key(
        table=_S,
        name="broadcast_reply",
        type=Type.BOOLEAN,
        default=False,
        help="Unit id 0 is broadcast: write functions only, sent to every line with "
        "broadcast = true. The specification gives no answer to a broadcast; true answers "
        "the master with what a single slave would have answered (the echo), once the frame "
        "is on the wire.",
    ),
    Key(
        table=_S,
        name="refuse_functions",
        type=Type.FUNCTION_CODES,
        default=[],
        low=1,
        high=127,
        help="Function codes answered locally with exception 0x01 (Illegal Function) on "
        "every listener, like [8] to keep diagnostics off the bus.",
    ),
    Key(
        table=_S,
        name="allow",
        type=Type.NETWORKS,
        default=[],
        help="Source addresses or networks every listener accepts (empty: any); others are "
        "closed at accept, before any byte. A listener's own allow list applies too.",
        flag=Flag(
            name="--allow",
            metavar="CIDR",
            repeat=True,
            help="accept masters only "
            "from this address or network, on every listener (repeatable); others "
            "are closed at accept",
        ),
    ),
    Key(
        table=_S,
        name="read_only",
        type=Type.BOOLEAN,
        default=False,
        help="true: every listener refuses anything but reads (exception 0x01).",
        flag=Flag(name="--read-only", help="every listener refuses anything but reads (0x01)"),
    ),
    Key(
        table=_S,
        name="tls_handshake_timeout",
        type=Type.SECONDS,
        default=10.0,
        low=0.1,
        high=600.0,
        help="Seconds a TLS master has to finish its handshake (tls listeners) before it is "
        "disconnected.",
    ),
    Key(
        table=_S,
        name="policy",
        type=Type.TEXT,
        show=Show.COMMENTED,
        example='"plant"',
        help='The policy of the "tcp" listener (a [policies.NAME] table). None: every '
        "request is served, except FC 8 subfunction 4 (Force Listen Only Mode) unless a "
        'rule names "8:4".',
    ),
)


def _serial_format(table: Table, only: str, reload: Reload, flags: bool) -> tuple[Key, ...]:
    """The format of a serial line: a line's, or a serial-slave listener's."""
    return (
        Key(
            table=table,
            name="baudrate",
            type=Type.INTEGER,
            default=9600,
            low=50,
            high=4_000_000,
            only=only,
            reload=reload,
            help="Bits per second on the wire.",
            flag=Flag(
                name="--baudrate",
                metavar="N",
                scope=Scope.EVERY_LINE,
                help="baud rate of every line",
            )
            if flags
            else None,
        ),
        Key(
            table=table,
            name="data_bits",
            type=Type.INTEGER,
            default=8,
            low=7,
            high=8,
            only=only,
            reload=reload,
            auto="8; 7 on an ASCII line",
            help="Data bits per character: 8, or 7 (Modbus ASCII's default).",
            flag=Flag(
                name="--data-bits",
                choices=(7, 8),
                scope=Scope.EVERY_LINE,
                help="data bits of every line (8; ascii: 7)",
            )
            if flags
            else None,
        ),
        Key(
            table=table,
            name="parity",
            type=Type.CHOICE,
            default="N",
            choices=("N", "E", "O"),
            only=only,
            reload=reload,
            auto='"N"; "E" on an ASCII line',
            help='"N", "E" or "O". The Modbus default is "E" with 1 stop bit; many devices '
            'use "N" with 2 or 1.',
            flag=Flag(
                name="--parity",
                choices=("N", "E", "O"),
                scope=Scope.EVERY_LINE,
                help="parity of every line",
            )
            if flags
            else None,
        ),
        Key(
            table=table,
            name="stop_bits",
            type=Type.ONE_OF,
            default=1,
            choices=(1, 1.5, 2),
            only=only,
            reload=reload,
            help="Stop bits: 1, 1.5 or 2.",
            flag=Flag(
                name="--stopbits",
                choices=(1, 2),
                scope=Scope.EVERY_LINE,
                help="stop bits of every line",
            )
            if flags
            else None,
        ),
    )


def _ascii_keys(table: Table, only: str, echo_only: str, reload: Reload) -> tuple[Key, ...]:
    """What an ASCII line, and an adapter that echoes, need."""
    return (
        Key(
            table=table,
            name="inter_char_timeout",
            type=Type.SECONDS,
            default=1.0,
            low=0.001,
            high=60.0,
            only=only,
            reload=reload,
            show=Show.COMMENTED,
            help="ASCII only: a frame whose characters stop for this many seconds is dropped.",
        ),
        Key(
            table=table,
            name="echo",
            type=Type.BOOLEAN,
            default=False,
            reload=reload,
            only=echo_only,
            help="The adapter hands back every byte the gateway sends (half-duplex, no echo "
            "suppression): drop exactly the echo of each frame sent.",
        ),
    )


LISTENERS = (
    Key(
        table=_LS,
        name="name",
        type=Type.TEXT,
        auto="the protocol",
        reload=Reload.RESTART,
        show=Show.BLOCK,
        help="A short name of letters, digits, - or _, unique among the listeners; used in "
        "logs, metrics and messages.",
    ),
    Key(
        table=_LS,
        name="protocol",
        type=Type.CHOICE,
        default="tcp",
        reload=Reload.RESTART,
        choices=("tcp", "tls", "rtu-over-tcp", "serial-slave"),
        show=Show.BLOCK,
        help='"tcp" (Modbus TCP), "tls" (Modbus/TCP Security: TLS 1.2 or newer, client '
        "certificates required, the role from the certificate's extension "
        '1.3.6.1.4.1.50316.802.1), "rtu-over-tcp" (masters sending bare RTU frames over TCP, '
        'one request at a time per connection) or "serial-slave" (reverse mode: the gateway '
        "answers RTU or ASCII masters on a serial line of its own as the slaves it routes).",
    ),
    Key(
        table=_LS,
        name="listen",
        type=Type.ADDRESS,
        default="0.0.0.0:502",
        show=Show.BLOCK,
        auto="0.0.0.0:502; 0.0.0.0:802 for tls",
        reload=Reload.RESTART,
        only='protocol = "tcp", "tls" or "rtu-over-tcp"',
        help="The address to listen on.",
        flag=Flag(
            name="--tls-listen",
            metavar="HOST:PORT",
            scope=Scope.TLS_LISTENER,
            help="Modbus/TCP Security (TLS) address, listener 'tls' (802 is the "
            "standard port); needs --tls-cert, --tls-key, --tls-ca",
        ),
    ),
    Key(
        table=_LS,
        name="cert",
        type=Type.FILE,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="The server's certificate chain (PEM, leaf first); read again at every reload.",
        flag=Flag(
            name="--tls-cert",
            metavar="FILE",
            scope=Scope.TLS_LISTENER,
            help="the server's certificate chain, PEM (leaf first)",
        ),
    ),
    Key(
        table=_LS,
        name="key",
        type=Type.FILE,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="The server's private key (PEM); read again at every reload.",
        flag=Flag(
            name="--tls-key",
            metavar="FILE",
            scope=Scope.TLS_LISTENER,
            help="the server's private key, PEM",
        ),
    ),
    Key(
        table=_LS,
        name="ca",
        type=Type.FILE,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="The CA certificates client certificates must chain to (PEM); read again at "
        "every reload.",
        flag=Flag(
            name="--tls-ca",
            metavar="FILE",
            scope=Scope.TLS_LISTENER,
            help="CA certificates client certificates must chain to, PEM",
        ),
    ),
    Key(
        table=_LS,
        name="crl",
        type=Type.FILE,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="Certificate revocation lists (PEM, one per CA that issues client certificates): "
        "a listed client certificate is refused at the handshake, and its open connections "
        "close at the reload that brings the list. Read again at every reload; an unreadable "
        "list, or one past its nextUpdate, stops start-up and rejects the reload.",
        flag=Flag(
            name="--tls-crl",
            metavar="FILE",
            scope=Scope.TLS_LISTENER,
            help="certificate revocation lists for client certificates, PEM",
        ),
    ),
    Key(
        table=_LS,
        name="forward_secrecy_only",
        type=Type.BOOLEAN,
        default=False,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="false offers TLS_RSA_WITH_AES_128_CBC_SHA256 (AES128-SHA256, the suite "
        "MB-TCP-Security R-14 requires; RSA key exchange, so an RSA server certificate) after "
        "the ECDHE suites, which every client able to use them still gets; true offers only "
        "suites with forward secrecy. NULL suites are always refused.",
    ),
    Key(
        table=_LS,
        name="session_resumption",
        type=Type.BOOLEAN,
        default=False,
        only='protocol = "tls"',
        show=Show.BLOCK,
        help="true lets masters resume TLS sessions (session tickets, TLS 1.2 and 1.3) for "
        "OpenSSL's default lifetime of 7,200 s, which Python's ssl cannot change; a resumed "
        "session skips the certificate check (a CRL update reaches it only through the "
        "reload's re-evaluation of open connections). false: every connection does a full "
        "handshake.",
    ),
    Key(
        table=_LS,
        name="allow",
        type=Type.NETWORKS,
        default=[],
        show=Show.BLOCK,
        only='protocol = "tcp", "tls" or "rtu-over-tcp"',
        help="Source addresses or networks this listener accepts (empty: any), besides "
        "server.allow.",
    ),
    Key(
        table=_LS,
        name="read_only",
        type=Type.BOOLEAN,
        default=False,
        show=Show.BLOCK,
        help="true: this listener refuses anything but reads (0x01); server.read_only applies too.",
    ),
    Key(
        table=_LS,
        name="policy",
        type=Type.TEXT,
        show=Show.BLOCK,
        help="The listener's policy, a [policies.NAME] table. None: every request is served "
        '(except FC 8:4 unless a rule names "8:4").',
    ),
    Key(
        table=_LS,
        name="device",
        type=Type.TEXT,
        only=_SLAVE,
        reload=Reload.RESTART,
        show=Show.BLOCK,
        help="The serial device the gateway answers masters on, its own (not a line's).",
    ),
    *_serial_format(_LS, _SLAVE, Reload.RESTART, flags=False),
    Key(
        table=_LS,
        name="units",
        type=Type.UNITS,
        default=[],
        only=_SLAVE,
        reload=Reload.RESTART,
        show=Show.BLOCK,
        auto="every routed unit",
        help='The units it answers for: numbers and "A-B" ranges; it stays silent for others.',
    ),
    Key(
        table=_LS,
        name="framing",
        type=Type.CHOICE,
        default="rtu",
        choices=("rtu", "ascii"),
        only=_SLAVE,
        reload=Reload.RESTART,
        show=Show.BLOCK,
        help='What the masters on its line speak: "rtu", or "ascii" (\':\' to CR LF with '
        "LRC, 7E1 unless data_bits/parity).",
    ),
    *_ascii_keys(_LS, 'protocol = "serial-slave", framing = "ascii"', _SLAVE, Reload.RESTART),
)

METRICS = (
    Key(
        table=_M,
        name="listen",
        type=Type.ADDRESS_OR_OFF,
        default="127.0.0.1:9502",
        reload=Reload.RESTART,
        help='HTTP endpoint for /metrics, /healthz, /readyz and the status page; "auto" '
        "takes a free port on 127.0.0.1 (the start-up log names it), so that instances run "
        'side by side; "off" disables it.',
        flag=Flag(
            name="--metrics",
            metavar="HOST:PORT|auto|off",
            help="HTTP endpoint for "
            "/metrics, /healthz, /readyz and the status page (default 127.0.0.1:9502; "
            "auto: a free port, logged)",
        ),
    ),
    Key(
        table=_M,
        name="max_connections",
        type=Type.INTEGER,
        default=32,
        low=1,
        high=1024,
        reload=Reload.RESTART,
        help="HTTP connections open at once (scrapers, health checks); at the cap a "
        "connection still sending its request head is closed to make room, else the new one "
        "is refused.",
    ),
    Key(
        table=_M,
        name="header_timeout",
        type=Type.SECONDS,
        default=5.0,
        low=0.1,
        high=60.0,
        reload=Reload.RESTART,
        help="Seconds a client has to send its request head before the connection is closed.",
    ),
    Key(
        table=_M,
        name="max_connections_per_source",
        type=Type.INTEGER,
        default=8,
        low=0,
        high=1024,
        reload=Reload.RESTART,
        help="HTTP connections one source address may hold at once, streams included (0 = "
        "no cap); more are closed at accept, so one client cannot take every stream slot.",
    ),
    Key(
        table=_M,
        name="allowed_hosts",
        type=Type.TEXT,
        default=[],
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='["gateway.plant.example"]',
        help="Host names (a list) the status page, /status and /trace answer to, besides "
        "loopback names and the endpoint's own address; another Host header gets 421, so a "
        "web page cannot reach them through DNS rebinding. /metrics, /healthz and /readyz "
        "answer whatever the Host.",
    ),
    Key(
        table=_M,
        name="status_token",
        type=Type.TEXT,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"a long random string"',
        help='A token the status page and /status ask for: "Authorization: Bearer TOKEN", '
        "or a cookie set by opening /?token=TOKEN once (docs/http-endpoint.md). None: no "
        "token.",
    ),
    Key(
        table=_M,
        name="trace_token",
        type=Type.TEXT,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"another long random string"',
        help="A token /trace asks for (it carries register values), given as status_token "
        "is. None: no token.",
    ),
    Key(
        table=_M,
        name="tls_cert",
        type=Type.FILE,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"/etc/modbus-gateway/http.crt"',
        help="Serve the endpoint over TLS (HTTPS) with this certificate chain (PEM, leaf "
        "first); needs tls_key.",
    ),
    Key(
        table=_M,
        name="tls_key",
        type=Type.FILE,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"/etc/modbus-gateway/http.key"',
        help="The private key of tls_cert (PEM).",
    ),
    Key(
        table=_M,
        name="tls_ca",
        type=Type.FILE,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"/etc/modbus-gateway/http-clients.pem"',
        help="With tls_cert: every HTTPS client must present a certificate chaining to "
        "these CAs (PEM), scrapers included.",
    ),
)

LOGGING = (
    Key(
        table=_LG,
        name="level",
        type=Type.CHOICE,
        default="info",
        reload=Reload.RESTART,
        choices=("debug", "info", "warning", "error"),
        help="The least severe level logged.",
        flag=Flag(
            name="--log-level",
            choices=("debug", "info", "warning", "error"),
            help="the least severe level logged",
        ),
    ),
    Key(
        table=_LG,
        name="format",
        type=Type.CHOICE,
        default="text",
        choices=("text", "json"),
        reload=Reload.RESTART,
        help='"text", or "json": one JSON object per line.',
        flag=Flag(
            name="--log-format",
            choices=("text", "json"),
            help="text, or json: one JSON object per line",
        ),
    ),
)

AUDIT = (
    Key(
        table=_A,
        name="path",
        type=Type.TEXT,
        show=Show.COMMENTED,
        reload=Reload.RESTART,
        example='"/var/log/modbus-gateway/audit.jsonl"',
        help="The audit log (docs/audit.md): every request that is not a read and reached a "
        "slave or was denied, every configuration load or reload and every connection an "
        'allow list refused, one hash-chained JSON line each; "-" is standard error. '
        "SIGHUP reopens it (logrotate). None: no audit log.",
        flag=Flag(
            name="--audit-log",
            metavar="PATH",
            help="write the audit log (writes, "
            "denials, reloads, refused connections) to PATH; - for standard error",
        ),
    ),
)

REDUNDANCY = (
    Key(
        table=_PAIR,
        name="peer",
        type=Type.ADDRESS,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"192.0.2.12:9502"',
        help="The other gateway's HTTP endpoint ([metrics] listen), polled for its role over "
        "HTTPS when [metrics] tls_cert is set, with status_token when set. None: no pair.",
        flag=Flag(
            name="--redundancy-peer",
            metavar="HOST:PORT",
            help="pair with the gateway whose HTTP endpoint is HOST:PORT",
        ),
    ),
    Key(
        table=_PAIR,
        name="peer_modbus",
        type=Type.ADDRESS,
        reload=Reload.RESTART,
        show=Show.COMMENTED,
        example='"192.0.2.12:502"',
        help="The other gateway's Modbus TCP listener: while standby, masters' requests are "
        "forwarded there, one connection per master. Required with peer.",
        flag=Flag(
            name="--redundancy-peer-modbus",
            metavar="HOST:PORT",
            help="the paired gateway's Modbus TCP listener, for forwarding",
        ),
    ),
    Key(
        table=_PAIR,
        name="priority",
        type=Type.INTEGER,
        default=100,
        low=0,
        high=255,
        reload=Reload.RESTART,
        help="Decides only between two gateways that start within one lease of each other "
        "(higher first); a gateway that starts beside an active peer stays standby.",
        flag=Flag(
            name="--redundancy-priority",
            metavar="N",
            help="the pair's priority, 0..255 (default 100; higher goes first)",
        ),
    ),
    Key(
        table=_PAIR,
        name="lease",
        type=Type.SECONDS,
        default=1.0,
        low=0.2,
        high=30.0,
        reload=Reload.RESTART,
        help="Seconds the active's claim lasts; it renews it while its evidence allows and "
        "checks it before every frame it transmits.",
    ),
    Key(
        table=_PAIR,
        name="takeover_after",
        type=Type.SECONDS,
        default=1.5,
        low=0.3,
        high=60.0,
        reload=Reload.RESTART,
        help="Seconds of a bus without master frames (besides an expired lease and a peer "
        "not active) before the standby takes over; longer than the lease plus 0.3 s, the "
        "time the active's frame may take to be heard.",
    ),
    Key(
        table=_PAIR,
        name="keepalive",
        type=Type.TEXT,
        default="auto",
        reload=Reload.RESTART,
        help="What the active reads when it has sent nothing for half a lease, so that the "
        'standby hears it: "auto" (one holding register of a slave heard answering), '
        '"SLAVE:REGISTER" (that holding register of that slave address, on every line) or '
        '"off".',
    ),
)

LINES = (
    Key(
        table=_L,
        name="kind",
        type=Type.CHOICE,
        default="rtu",
        choices=_LINE_KINDS,
        reload=Reload.REOPENS,
        help='What the line is: "rtu" (Modbus RTU on a serial device, the default), "ascii" '
        "(Modbus ASCII: ':', hex characters, LRC, CR LF; 7E1 by default, its automatic "
        'timeout holds 513 characters), "rtu-over-tcp" (RTU frames over a TCP connection to '
        'a serial device server in raw socket mode), "tcp" (a Modbus TCP slave, MBAP under '
        'the gateway\'s own transaction ids) or "tls" (a Modbus/TCP Security slave).',
        flag=Flag(
            name="--framing",
            choices=("rtu", "ascii"),
            scope=Scope.EVERY_LINE,
            help="what every serial line speaks: rtu (default) or ascii (7E1 unless --parity)",
        ),
    ),
    Key(
        table=_L,
        name="device",
        type=Type.TEXT,
        only=_SERIAL,
        reload=Reload.REOPENS,
        example='"/dev/ttyUSB0"',
        help='A device node, or a pyserial URL for a serial server: "socket://10.0.0.5:4001", '
        '"rfc2217://10.0.0.5:4001". Prefer /dev/serial/by-id/... names: they survive '
        "re-plugging. Required on a serial line.",
    ),
    *_ascii_keys(_L, 'kind = "ascii"', "", Reload.APPLIED),
    *_serial_format(_L, "", Reload.REOPENS, flags=True),
    Key(
        table=_L,
        name="timeout",
        type=Type.SECONDS,
        default="auto",
        low=0.001,
        high=60.0,
        auto="learned per slave and function (per line on tcp and tls): the predicted answer's "
        "transmission plus a high quantile of the slave's turnaround, between 0.1 s (0.2 s on "
        "a network line) and max_timeout; initial_timeout until it first answers",
        help='Seconds from the end of the request to the end of the slave\'s answer. "auto" '
        "learns each slave's timing, so a slave slow on some requests keeps a timeout that "
        "covers them and a fast slave's silence is noticed quickly; a retry waits twice as "
        "long. A number is fixed for every slave, as is a slave_timeouts entry for its slave.",
        flag=Flag(
            name="--timeout",
            metavar="SECONDS",
            scope=Scope.EVERY_LINE,
            help="fixed response timeout of every line (default auto: learned)",
        ),
    ),
    Key(
        table=_L,
        name="initial_timeout",
        type=Type.SECONDS,
        default=1.0,
        low=0.001,
        high=60.0,
        help='timeout = "auto": the turnaround allowed to a slave (or one of its functions) '
        "never heard from yet, the common 1 s of the serial-line guide.",
    ),
    Key(
        table=_L,
        name="max_timeout",
        type=Type.SECONDS,
        default=3.0,
        low=0.001,
        high=60.0,
        help='timeout = "auto": the most a learned turnaround, or a retry\'s backed-off '
        "one, may reach.",
    ),
    Key(
        table=_L,
        name="retries",
        type=Type.INTEGER,
        default=1,
        low=0,
        high=10,
        help="Times a request is sent again after a timeout or a garbled answer, before "
        "exception 0x0B. Only requests without side effects are retried: FC 1-4, 7, 11, 12, "
        "17, 20, 24, 43/14 and FC 8 subfunction 0.",
        flag=Flag(
            name="--retries",
            metavar="N",
            scope=Scope.EVERY_LINE,
            help="retries after a timeout or bad CRC (default 1)",
        ),
    ),
    Key(
        table=_L,
        name="retry_unsafe",
        type=Type.BOOLEAN,
        default=False,
        aliases=("retry_writes",),
        help="Writes, FC 23, diagnostics that change state and user-defined codes are sent "
        "once: if the slave executed one but its answer was lost, a retry executes it twice "
        "(a counter increment, a pulse, a queue push). Set true only if every such request "
        "on this line is idempotent.",
    ),
    Key(
        table=_L,
        name="late_answer_window",
        type=Type.SECONDS,
        default="auto",
        low=0.0,
        high=60.0,
        auto="until proof that the lost answer cannot come (no time limit)",
        help="After a timeout or a garbled answer, the slave's answer may still arrive: "
        "nothing whose answer could be confused with it (same slave, function and byte count "
        "or echo) is sent to that slave until proof that it cannot come (the answer heard, or "
        "a later request of another answer length answered; the gateway sends such a read "
        "itself when a request waits). A number bounds the wait in seconds instead and turns "
        "those proof reads off; other slaves are served meanwhile.",
    ),
    Key(
        table=_L,
        name="frame_gap",
        type=Type.SECONDS,
        default="auto",
        low=0.0,
        high=1.0,
        show=Show.COMMENTED,
        example="0.00175",
        auto="t3.5 (3.5 characters, 1.75 ms above 19200 baud); one character on ASCII; 0 "
        "on a network line",
        help="Silence kept before every request, in seconds. Use 0 for a serial server "
        "reached by URL that does its own timing.",
        flag=Flag(
            name="--frame-gap",
            metavar="SECONDS",
            scope=Scope.EVERY_LINE,
            help="silence before every request (default t3.5; 0 for serial servers)",
        ),
    ),
    Key(
        table=_L,
        name="silence",
        type=Type.SECONDS,
        default="auto",
        low=0.0,
        high=10.0,
        show=Show.COMMENTED,
        example="0.00175",
        auto="t3.5, at least 0.05 s on a network line; inter_char_timeout on ASCII",
        help="Silence that ends an answer whose length cannot be predicted from its function "
        "code (user-defined codes).",
    ),
    Key(
        table=_L,
        name="broadcast",
        type=Type.BOOLEAN,
        default=True,
        help="Send unit-0 broadcasts on this line, then wait broadcast_turnaround seconds "
        "before the next request so slaves can execute it.",
    ),
    Key(
        table=_L,
        name="broadcast_turnaround",
        type=Type.SECONDS,
        default=0.1,
        low=0.0,
        high=10.0,
        help="Seconds the line stays quiet after a broadcast.",
    ),
    Key(
        table=_L,
        name="max_queue",
        type=Type.INTEGER,
        default=256,
        low=1,
        high=100_000,
        help="Requests waiting for this line; when full, the master with the longest queue "
        "loses its newest request (0x0A) to a master with a shorter one; past that a request "
        "gets 0x0A at once.",
    ),
    Key(
        table=_L,
        name="max_queue_per_master",
        type=Type.INTEGER,
        default=32,
        low=1,
        high=10_000,
        help="Requests one master may have waiting on this line or on its wire (one that "
        "fails waits again for its retry); past this it gets 0x06 (device busy).",
    ),
    Key(
        table=_L,
        name="max_queue_wait",
        type=Type.SECONDS,
        default=5.0,
        low=0.0,
        high=3600.0,
        help="Seconds a request may wait in the line's queue: one still unsent after this is "
        "answered 0x0B without using the line (its master has given up on it by then), and "
        "the slave's health is not touched. 0: no limit.",
    ),
    Key(
        table=_L,
        name="noisy_after",
        type=Type.SECONDS,
        default="auto",
        low=0.0,
        high=3600.0,
        auto="3 x the longest timeout (learned: at most 3 x max_timeout)",
        help="Seconds without a usable gap (a babbling slave or transceiver) before waiting "
        "requests are answered 0x0B and the line is reported noisy.",
    ),
    Key(
        table=_L,
        name="rs485",
        type=Type.BOOLEAN,
        default=False,
        only=_SERIAL,
        reload=Reload.REOPENS,
        help="Kernel RS485 mode (adapters whose driver supports TIOCSRS485), with RTS "
        "direction control as the next four keys say.",
    ),
    Key(
        table=_L,
        name="rs485_rts_level_for_tx",
        type=Type.BOOLEAN,
        default=True,
        only=_SERIAL,
        reload=Reload.REOPENS,
        help="RS485 mode: the RTS level while sending.",
    ),
    Key(
        table=_L,
        name="rs485_rts_level_for_rx",
        type=Type.BOOLEAN,
        default=False,
        only=_SERIAL,
        reload=Reload.REOPENS,
        help="RS485 mode: the RTS level while receiving.",
    ),
    Key(
        table=_L,
        name="rs485_delay_before_tx",
        type=Type.SECONDS,
        default=0.0,
        low=0.0,
        high=1.0,
        only=_SERIAL,
        reload=Reload.REOPENS,
        help="RS485 mode: seconds between raising RTS and sending.",
    ),
    Key(
        table=_L,
        name="rs485_delay_after_tx",
        type=Type.SECONDS,
        default=0.0,
        low=0.0,
        high=1.0,
        only=_SERIAL,
        reload=Reload.REOPENS,
        help="RS485 mode: seconds between the last byte sent and dropping RTS.",
    ),
    Key(
        table=_L,
        name="units",
        type=Type.UNITS,
        default=[],
        example='["1-10"]',
        help="TCP unit ids routed to this line with the same slave address: numbers and "
        '"A-B" ranges.',
    ),
    Key(
        table=_L,
        name="slave_timeouts",
        type=Type.TIMEOUTS,
        default={},
        help="Per-slave response timeouts overriding timeout: a table of slave = seconds, "
        'keys quoted, like { "5" = 0.3 }.',
    ),
    Key(
        table=_L,
        name="names",
        type=Type.NAMES,
        default={},
        example='{ "1" = "plc" }',
        show=Show.COMMENTED,
        help="Names of the line's slaves for the status page: a table of slave = name, keys "
        'quoted, like { "1" = "plc", "2" = "meter" }. A named slave is listed there before it '
        "has answered.",
    ),
    Key(
        table=_L,
        name="dead_after",
        type=Type.INTEGER,
        default=3,
        low=0,
        high=1000,
        help="Dead-slave isolation: after this many transactions in a row that got no answer "
        "(after their retries) the slave is answered 0x0B at once instead of holding the "
        "line for the timeout; one probe at a time goes to it, and its first answer brings "
        "it back. Only timeouts of function codes the slave has answered before count, so a "
        "master sending a code the slave ignores cannot isolate it. 0 disables isolation.",
    ),
    Key(
        table=_L,
        name="reconnect_after",
        type=Type.INTEGER,
        default=3,
        low=0,
        high=1000,
        help="On tcp, tls and rtu-over-tcp lines: a connection that answered before and then "
        "misses this many answers in a row, with nothing heard on it from any slave, is "
        "closed and opened again (with back-off). Reads on the wire then are sent again on "
        "the new connection, other requests are answered 0x0B, and the timeouts on the "
        "silent connection do not count against the slaves. 0 never reconnects.",
    ),
    Key(
        table=_L,
        name="probe_interval",
        type=Type.SECONDS,
        default=1.0,
        low=0.01,
        high=3600.0,
        help="Seconds before the first probe of an isolated slave; the interval then "
        "doubles up to probe_max_interval.",
    ),
    Key(
        table=_L,
        name="probe_max_interval",
        type=Type.SECONDS,
        default=30.0,
        low=0.01,
        high=86_400.0,
        help="The longest interval between probes of an isolated slave.",
    ),
    Key(
        table=_L,
        name="probe_share",
        type=Type.NUMBER,
        default=0.05,
        low=0.0,
        high=1.0,
        help='After one counted timeout a slave is "suspect": at most one of its requests '
        "waits, behind the healthy slaves', others are answered 0x0B at once. Suspect and "
        "dead slaves together get at most this share of the line's time while healthy "
        "slaves have requests waiting.",
    ),
    Key(
        table=_L,
        name="coalesce",
        type=Type.BOOLEAN,
        default=True,
        help="Identical reads (FC 1-4, same slave, address and quantity) from different "
        "masters that wait in the queue are served by one transaction. A read never joins a "
        "transaction already on the wire, nor one queued before a write (or any non-read) "
        "to the same slave.",
    ),
    Key(
        table=_L,
        name="cache",
        type=Type.TABLES,
        default=[],
        show=Show.BLOCK,
        help="Read cache, off unless rules are given: [[lines.NAME.cache]] "
        "tables (below). Any write (or any other non-read request) to the slave through this "
        "gateway drops its cached responses. Safe only for values that nothing else changes "
        "faster than max_age: measurements polled by many masters, not set-points written by "
        "another master on another gateway or by the device. A read that a [[poll]] block "
        "covers is served by the block (agent mode, docs/agent-mode.md).",
    ),
    Key(
        table=_L,
        name="address",
        type=Type.ADDRESS,
        only=_NETWORK,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="The device server's or slave's address, HOST:PORT (replaces device); a tls "
        "line's port is 802 when none is given.",
    ),
    Key(
        table=_L,
        name="connect_timeout",
        type=Type.SECONDS,
        default=3.0,
        low=0.01,
        high=600.0,
        only=_NETWORK,
        show=Show.BLOCK,
        help="Seconds a connection attempt may take.",
    ),
    Key(
        table=_L,
        name="connect_delay",
        type=Type.SECONDS,
        default=0.0,
        low=0.0,
        high=60.0,
        only=_NETWORK,
        show=Show.BLOCK,
        help="Seconds the line stays down (0x0A) after connecting, for device servers that "
        "drop what arrives while they set up their serial side.",
    ),
    Key(
        table=_L,
        name="max_in_flight",
        type=Type.INTEGER,
        default=1,
        low=1,
        high=MAX_IN_FLIGHT,
        only='kind = "tcp" or "tls"',
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="Requests outstanding at once on the connection. Many devices take one at a "
        "time: raise it only for those that answer several. One master's requests to one "
        "unit keep read-after-write order.",
        flag=Flag(
            name="--max-in-flight",
            metavar="N",
            scope=Scope.MBAP_LINES,
            help="requests outstanding at once on the connection of a tcp or tls line "
            "(1..64; default 1: many devices take one at a time)",
        ),
    ),
    Key(
        table=_L,
        name="cert",
        type=Type.FILE,
        only=_TLS,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="The gateway's client certificate chain (PEM, leaf first).",
        flag=Flag(
            name="--modbus-tls-cert",
            metavar="FILE",
            scope=Scope.TLS_LINES,
            help="the gateway's client certificate chain for tls lines, PEM (leaf first)",
        ),
    ),
    Key(
        table=_L,
        name="key",
        type=Type.FILE,
        only=_TLS,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="The private key of that certificate (PEM, unencrypted).",
        flag=Flag(
            name="--modbus-tls-key",
            metavar="FILE",
            scope=Scope.TLS_LINES,
            help="the private key of --modbus-tls-cert, PEM",
        ),
    ),
    Key(
        table=_L,
        name="ca",
        type=Type.FILE,
        only=_TLS,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="The CA certificates the slave's certificate must chain to (PEM).",
        flag=Flag(
            name="--modbus-tls-ca",
            metavar="FILE",
            scope=Scope.TLS_LINES,
            help="CA certificates the tls slave's certificate must chain to, PEM",
        ),
    ),
    Key(
        table=_L,
        name="server_name",
        type=Type.TEXT,
        only=_TLS,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        auto="the address's host",
        help="The name the slave's certificate must carry.",
        flag=Flag(
            name="--modbus-tls-server-name",
            metavar="NAME",
            scope=Scope.TLS_LINES,
            help="the name the tls slave's certificate must carry (default: the host "
            "of --modbus-tls)",
        ),
    ),
    Key(
        table=_L,
        name="check_server_name",
        type=Type.BOOLEAN,
        default=True,
        only=_TLS,
        reload=Reload.REOPENS,
        show=Show.BLOCK,
        help="false skips only the check of server_name (warned about), never the chain's.",
    ),
    Key(
        table=_L,
        name="tls_handshake_timeout",
        type=Type.SECONDS,
        default=10.0,
        low=0.1,
        high=600.0,
        only=_TLS,
        show=Show.BLOCK,
        help="Seconds the TLS handshake with the slave may take; the line stays down (0x0A) "
        "while it fails.",
    ),
)

CACHE = (
    Key(
        table=_C,
        name="unit",
        type=Type.INTEGER,
        default=1,
        low=1,
        high=247,
        show=Show.BLOCK,
        help="The slave address whose reads the rule covers.",
    ),
    Key(
        table=_C,
        name="function",
        type=Type.INTEGER,
        default=3,
        low=1,
        high=4,
        show=Show.BLOCK,
        help="The read function: 1, 2, 3 or 4.",
    ),
    Key(
        table=_C,
        name="start",
        type=Type.INTEGER,
        default=0,
        low=0,
        high=65535,
        show=Show.BLOCK,
        help="The first address of the range.",
    ),
    Key(
        table=_C,
        name="count",
        type=Type.INTEGER,
        default=1,
        low=1,
        high=65536,
        show=Show.BLOCK,
        help="How many addresses the range holds.",
    ),
    Key(
        table=_C,
        name="max_age",
        type=Type.SECONDS,
        default=1.0,
        low=0.0,
        high=3600.0,
        show=Show.BLOCK,
        help="Reads wholly inside the range are answered from the last good response up to "
        "this many seconds old.",
    ),
)

ROUTES = (
    Key(
        table=_RT,
        name="unit",
        type=Type.INTEGER,
        low=1,
        high=255,
        show=Show.BLOCK,
        help="The TCP unit id this route answers for (required).",
    ),
    Key(
        table=_RT,
        name="line",
        type=Type.TEXT,
        show=Show.BLOCK,
        help="The name of a configured line (required).",
    ),
    Key(
        table=_RT,
        name="slave",
        type=Type.INTEGER,
        low=1,
        high=247,
        show=Show.BLOCK,
        auto="the unit id (1 for units above 247)",
        help="The slave address on that line.",
    ),
)

_POLL, _POLLING = Table.POLL, Table.POLLING

POLL = (
    Key(
        table=_POLL,
        name="unit",
        type=Type.INTEGER,
        low=1,
        high=255,
        show=Show.BLOCK,
        help="The unit id masters use for the block's slave (required); routed as any "
        "request, so the block lives on the unit's line and slave address.",
    ),
    Key(
        table=_POLL,
        name="function",
        type=Type.INTEGER,
        default=3,
        low=1,
        high=4,
        show=Show.BLOCK,
        help="The read function the gateway polls and answers from memory: 1, 2, 3 or 4.",
    ),
    Key(
        table=_POLL,
        name="address",
        type=Type.INTEGER,
        default=0,
        low=0,
        high=65535,
        show=Show.BLOCK,
        help="The block's first address.",
    ),
    Key(
        table=_POLL,
        name="count",
        type=Type.INTEGER,
        low=1,
        high=2000,
        show=Show.BLOCK,
        help="How many registers (at most 125) or bits (at most 2000) the block holds "
        "(required); the block must end inside the 65,536 addresses.",
    ),
    Key(
        table=_POLL,
        name="every",
        type=Type.SECONDS,
        default=1.0,
        low=0.05,
        high=3600.0,
        show=Show.BLOCK,
        help="Seconds between polls. A due poll goes before the masters' waiting requests, "
        "never in the middle of a transaction.",
    ),
    Key(
        table=_POLL,
        name="max_age",
        type=Type.SECONDS,
        default="auto",
        low=0.05,
        high=86_400.0,
        auto="3 x every",
        show=Show.BLOCK,
        help="A master is never answered from memory with data older than this (counted from "
        "when the poll was sent); older, its read goes to the wire. At least every.",
    ),
)

POLLING = (
    Key(
        table=_POLLING,
        name="status_unit",
        type=Type.INTEGER,
        default=0,
        low=0,
        high=255,
        help="0: off. Else a unit id the gateway answers itself, FC 3 and FC 4 only, with two "
        "registers per [[poll]] block in configuration order: its data's age in tenths of a "
        "second (65535: never polled) and its state (0 fresh, 1 stale, 2 failing). 248-255 "
        "never collide with --serial's routes; a routed unit is an error.",
    ),
    Key(
        table=_POLLING,
        name="max_blocks",
        type=Type.INTEGER,
        default=256,
        low=1,
        high=10_000,
        help="The most [[poll]] blocks the configuration may declare (each keeps at most "
        "255 bytes of answer).",
    ),
)

POLICIES = (
    Key(
        table=_P,
        name="rules",
        type=Type.TEXT,
        show=Show.BLOCK,
        default=[],
        help="The policy's rules, [[policies.NAME.rules]] tables in order. A policy without "
        "rules refuses every request.",
    ),
)

RULES = (
    Key(
        table=_R,
        name="role",
        type=Type.TEXT,
        show=Show.BLOCK,
        auto="any",
        help="The role in the master's client certificate (tls listeners).",
    ),
    Key(
        table=_R,
        name="source",
        type=Type.NETWORKS,
        show=Show.BLOCK,
        auto="any",
        help="Source addresses or networks of the master.",
    ),
    Key(
        table=_R,
        name="units",
        type=Type.RANGES,
        low=0,
        high=255,
        show=Show.BLOCK,
        auto="any unit but broadcast (0)",
        help='Unit ids and "A-B" ranges, 0 for broadcast. A rule that names a unit covers '
        "that slave whatever unit id reaches it.",
    ),
    Key(
        table=_R,
        name="line",
        type=Type.TEXT,
        show=Show.BLOCK,
        auto="any",
        help="A line's name, or a list of them: the rule covers only requests routed to "
        "those lines (never an unrouted unit or a broadcast).",
    ),
    Key(
        table=_R,
        name="slave",
        type=Type.RANGES,
        low=1,
        high=247,
        show=Show.BLOCK,
        auto="any",
        help='Slave addresses and "A-B" ranges: the rule covers only requests '
        "routed to those slave addresses (on its line, if it names one).",
    ),
    Key(
        table=_R,
        name="functions",
        type=Type.FUNCTIONS,
        show=Show.BLOCK,
        auto="any",
        help='Function codes (3, "0x10"), names ("read_holding_registers") and FC 8 '
        'subfunctions ("8:4", "diagnostics:0") or FC 43 MEI types ("43:14").',
    ),
    Key(
        table=_R,
        name="addresses",
        type=Type.RANGES,
        low=0,
        high=65535,
        show=Show.BLOCK,
        auto="any",
        help='Addresses and "A-B" ranges; a request\'s whole range must be inside.',
    ),
    Key(
        table=_R,
        name="access",
        type=Type.CHOICE,
        default="read_write",
        choices=("read", "write", "read_write"),
        show=Show.BLOCK,
        help="What the rule grants: reads, writes, or both.",
    ),
)

KEYS = (
    *SERVER,
    *LISTENERS,
    *METRICS,
    *LOGGING,
    *AUDIT,
    *REDUNDANCY,
    *LINES,
    *CACHE,
    *ROUTES,
    *POLL,
    *POLLING,
    *POLICIES,
    *RULES,
)
