"""What is legal but probably wrong: the warnings ``check-config`` prints and the gateway
logs at start, each naming its key and what to do. Warnings, not errors: the configuration
is valid and runs.
"""

from __future__ import annotations

import ipaddress
import os

from ..core.framing import is_mbap
from ..core.policy import lint
from ..core.timing import t35, transmission_time
from .model import GatewayConfig, LineConfig, MetricsConfig
from .services import is_loopback

#: ``server.max_connections_per_source`` before fair share: a file that still sets it is warned.
OLD_PER_SOURCE_DEFAULT = 16


def config_warnings(config: GatewayConfig) -> list[str]:
    """Things that are legal but probably wrong, each naming its key (check-config, start).

    Warnings, not errors: a USB adapter may be plugged in after the gateway starts, and a
    line may be kept ready for units routed to it later.
    """
    warnings = list(config.renamed)
    routed_lines = {route.line for route in config.routes.values()}
    for line in config.lines:
        prefix = f"lines.{line.name}"
        if not line.is_url and not os.path.exists(line.device):
            warnings.append(
                f"{prefix}.device: {line.device} does not exist (yet); the gateway retries "
                "opening it, check the path (ls /dev/serial/by-id/)"
            )
        if line.kind == "tls" and not line.check_server_name:
            warnings.append(
                f"{prefix}.check_server_name: false: the slave's certificate must still chain "
                f"to {prefix}.ca, but any certificate that CA issued is taken for this slave; "
                "keep it only with a CA that issues this one device's certificate, else set "
                "server_name to the name in the slave's certificate"
            )
        if line.name not in routed_lines:
            warnings.append(
                f"{prefix}.units: no unit is routed to this line; add units = [...] or a "
                f'[[routes]] entry with line = "{line.name}"'
            )
    server, metrics = config.server, config.metrics
    if (
        metrics.enabled
        and server.port == metrics.port
        and server.port != 0
        and _hosts_overlap(server.host, metrics.host)
    ):
        warnings.append(
            f"metrics.listen: port {metrics.port} is also server.listen's (Modbus TCP); "
            "the second to bind fails: give one of them another port (the defaults are "
            "502 and 9502)"
        )
    if server.max_connections_per_source == OLD_PER_SOURCE_DEFAULT:
        warnings.append(
            f"server.max_connections_per_source: {OLD_PER_SOURCE_DEFAULT} was the default "
            "(the example file spelled it out); the default is now 0, no cap: at "
            "max_connections the address holding the most connections yields its longest-idle "
            "one. A cap of 16 refuses SCADA and OPC servers that open one connection per "
            "device; delete the line unless you mean to cap each address"
        )
    warnings += _poll_plan_warnings(config)
    return warnings + _endpoint_warnings(metrics) + _pair_warnings(config)


def _hosts_overlap(first: str, second: str) -> bool:
    wildcard = ("0.0.0.0", "::", "")
    return first == second or first in wildcard or second in wildcard


def poll_plan_share(line: LineConfig) -> float:
    """The share of ``line``'s wire time its poll plan needs: each block's request and
    answer frames with the silences around them, times its polls a second. 0.0 on a Modbus
    TCP or TLS line: its frames take no serial time."""
    if is_mbap(line.kind):
        return 0.0
    form = (line.baudrate, line.data_bits, line.parity, line.stop_bits)
    gap = line.frame_gap if line.frame_gap is not None else t35(*form)
    share = 0.0
    for block in line.polls:
        answer_bytes = (block.count + 7) // 8 if block.function in (1, 2) else 2 * block.count
        request, answer = 6, 3 + answer_bytes  # unit, PDU; unit, function, byte count, data
        if line.kind == "ascii":  # ':', two hex digits a byte, the LRC's two, CR LF
            request, answer = 1 + 2 * (request + 1) + 2, 1 + 2 * (answer + 1) + 2
        else:
            request, answer = request + 2, answer + 2  # the CRC
        wire = transmission_time(request + answer, *form) + 2 * gap
        share += wire / block.every
    return share


def _poll_plan_warnings(config: GatewayConfig) -> list[str]:
    """A line whose poll plan needs more than half its wire time leaves masters little."""
    warnings: list[str] = []
    for line in config.lines:
        share = poll_plan_share(line)
        if share > 0.5:
            warnings.append(
                f"poll: the blocks on line {line.name!r} need {share:.0%} of its wire time at "
                f"{line.baudrate} baud (more than half): masters' requests that memory cannot "
                "answer wait behind the polls; raise every, merge blocks, or poll fewer"
            )
    return warnings


def _endpoint_warnings(metrics: MetricsConfig) -> list[str]:
    """An HTTP endpoint whose documented protections are half set up, or not at all."""
    warnings: list[str] = []
    if not metrics.enabled:
        return warnings
    if metrics.status_token is not None and metrics.trace_token is None:
        warnings.append(
            "metrics.trace_token: not set while status_token is: /status and the page ask "
            "for a token, /trace (which carries register values) asks for none; set "
            'trace_token too (docs/http-endpoint.md, "Tokens")'
        )
    tokens = metrics.status_token is not None or metrics.trace_token is not None
    if not is_loopback(metrics.host) and not tokens and metrics.tls_cert is None:
        shown = metrics.host or "every address"
        warnings.append(
            f"metrics.listen: {shown} is reachable from the network, with neither "
            "status_token nor trace_token nor HTTPS (tls_cert): anyone who reaches it reads "
            "/status and /trace (register values) in clear; set the tokens and tls_cert, "
            "tls_key, or listen on 127.0.0.1"
        )
    return warnings


def _pair_warnings(config: GatewayConfig) -> list[str]:
    """A pair whose gateways cannot reach each other, that names its peer by name, or
    whose active lets the bus fall silent."""
    pair = config.redundancy
    if pair.peer is None:
        return []
    warnings: list[str] = []
    if pair.keepalive is None:
        warnings.append(
            'redundancy.keepalive: "off": an active with nothing to send lets its lease end '
            "half a lease after its last frame, steps down, and the pair takes turns on an "
            'idle bus (each takeover costs masters 1.5 to 2.5 s); write "auto", or '
            '"SLAVE:REGISTER" to name the register it reads'
        )
    remote = not is_loopback(pair.peer[0])
    if remote and is_loopback(config.metrics.host):
        warnings.append(
            f"metrics.listen: {config.metrics.host} is a loopback address: the peer at "
            f"{pair.peer[0]} cannot poll this gateway's /role; listen on an address it "
            "reaches"
        )
    if remote and is_loopback(config.server.host):
        warnings.append(
            f"server.listen: {config.server.host} is a loopback address: the peer cannot "
            "forward its masters' requests here while it stands by; listen on an address it "
            "reaches"
        )
    for key, (host, _) in (("peer", pair.peer), ("peer_modbus", pair.peer_modbus or pair.peer)):
        try:
            ipaddress.ip_address(host)
        except ValueError:
            warnings.append(
                f"redundancy.{key}: {host} is a name: write the peer's IP address (a standby "
                "refuses to forward requests that come from its peer's address, which it "
                "compares as written)"
            )
    return warnings


def policy_warnings(config: GatewayConfig) -> list[str]:
    """Rules that can never grant anything, unused policies, tls listeners without a policy."""
    warnings: list[str] = []
    status_unit = config.polling.status_unit
    own_units = frozenset({status_unit}) if status_unit else frozenset()
    used = {listener.policy for listener in config.listeners}
    for name in config.policies:
        if name not in used:
            warnings.append(
                f"policies.{name}: no listener uses it; set policy = {name!r} on "
                "a listener ([server] or [[listeners]]) or remove it"
            )
    for listener in config.listeners:
        if listener.policy is None:
            if listener.tls:
                warnings.append(
                    f"{listener.key_prefix}policy: tls listener {listener.name!r} has no policy: "
                    "every client certificate with a role has every right (the NULL role none)"
                )
            continue
        rules = config.policies.get(listener.policy, ())
        if not rules:
            warnings.append(
                f"policies.{listener.policy}: no rules, so listener "
                f"{listener.name!r} refuses every request"
            )
        warnings += lint(
            rules,
            listener=listener.name,
            tls=listener.tls,
            read_only=listener.read_only or config.server.read_only,
            allow=listener.allow or config.server.allow,
            routes=config.routes,
            own_units=own_units,
        )
    return warnings
