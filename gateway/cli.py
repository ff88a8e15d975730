"""Command line: flags and file → configuration → a running gateway (uvloop when importable)."""

from __future__ import annotations

import argparse
import asyncio
import copy
import logging
import sys
from collections.abc import Callable, Coroutine, Sequence
from importlib import resources
from typing import TYPE_CHECKING, Any, NoReturn

from . import __version__, build, schema
from .app import Gateway, reloader, run_until_signalled
from .config import (
    ConfigError,
    GatewayConfig,
    build_config,
    config_warnings,
    parse_host_port,
    policy_warnings,
    read_config_file,
)
from .core.framing import is_mbap
from .io.frame_trace import parse_function
from .io.http.endpoint import endpoint_tls
from .io.links.link import DeviceUnusableError, ListenerDeviceUnusableError
from .io.links.tls import client_context
from .io.listeners.tls import server_context
from .io.tls_setup import TlsSetupError
from .logs import setup_logging
from .schema import Key, Scope, Table, Type
from .trace import Tracer

if TYPE_CHECKING:  # the simulator loads in demo mode only
    from .sim.demo import DemoLine

log = logging.getLogger("gateway")

DEMO_LISTEN = "127.0.0.1:5020"


def _host_port(text: str) -> str:
    try:
        parse_host_port(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def _metrics_address(text: str) -> str:
    return text.lower() if text.lower() in ("off", "auto") else _host_port(text)


def _function_code(text: str) -> int:
    try:
        return parse_function(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors can be log records (JSON lines when asked)."""

    def __init__(self, *args: Any, log_errors: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.log_errors = log_errors

    def error(self, message: str) -> NoReturn:
        if not self.log_errors:
            super().error(message)
        log.error("%s: %s", self.prog, message, extra={"usage": self.format_usage().strip()})
        sys.exit(2)


def _requested_log_format(argv: Sequence[str]) -> str | None:
    """``--log-format`` read before parsing, so that errors of the parse itself follow it."""
    for index, arg in enumerate(argv):
        if arg == "--log-format" and index + 1 < len(argv):
            return argv[index + 1]
        if arg.startswith("--log-format="):
            return arg.partition("=")[2]
    return None


def build_parser(log_errors: bool = False) -> argparse.ArgumentParser:
    """The ``modbus-gateway`` argument parser (run mode)."""
    parser = _Parser(
        log_errors=log_errors,
        prog="modbus-gateway",
        description="Modbus TCP to Modbus RTU gateway. Subcommands: 'check-config FILE', "
        "'example-config', 'trace [OPTIONS]' (the same as --trace), 'trace --url "
        "http://HOST:PORT' (attach to a running gateway), 'scan' (find the slaves on a line), "
        "'audit verify FILE...' (check an audit log's hash chain).",
    )
    parser.add_argument(
        "--version", action="version", version=f"modbus-gateway {__version__} ({build()})"
    )
    parser.add_argument("--config", metavar="FILE", help="TOML configuration file")
    _add_source_flags(parser)
    overrides = parser.add_argument_group(
        "configuration overrides", "each sets a key of the file (docs/configuration.md)"
    )
    for key in schema.flagged():
        assert key.flag is not None
        overrides.add_argument(key.flag.name, **_flag_arguments(key))
    _add_run_flags(parser)
    return parser


def _add_source_flags(parser: argparse.ArgumentParser) -> None:
    """Flags that add a line or a listener rather than set one key."""
    parser.add_argument(
        "--serial",
        metavar="DEVICE_OR_URL",
        help="serial device or pyserial URL; without --config every unit 1..247 is routed to it",
    )
    parser.add_argument(
        "--rtu-over-tcp",
        metavar="HOST:PORT",
        type=_host_port,
        help="RTU over TCP to a serial device server (raw socket mode) "
        "instead of --serial; without --config every unit 1..247 is "
        "routed to it",
    )
    parser.add_argument(
        "--modbus-tcp",
        metavar="HOST:PORT",
        type=_host_port,
        help="a Modbus TCP slave (or another gateway) instead of --serial; "
        "without --config every unit 1..247 is routed to it",
    )
    parser.add_argument(
        "--modbus-tls",
        metavar="HOST[:PORT]",
        help="a Modbus/TCP Security slave (port 802 unless given) instead of "
        "--serial; needs --modbus-tls-cert, --modbus-tls-key, --modbus-tls-ca; "
        "without --config every unit 1..247 is routed to it",
    )
    parser.add_argument(
        "--rtu-over-tcp-listen",
        metavar="HOST:PORT",
        type=_host_port,
        help="also accept masters sending RTU frames over TCP here, listener 'rtu-over-tcp'",
    )
    parser.add_argument(
        "--serial-slave",
        metavar="DEVICE",
        help="also answer RTU masters on this serial device as the routed "
        "slaves (reverse mode), listener 'serial-slave'; the line format "
        "of --baudrate/--data-bits/--parity/--stopbits applies to it "
        "too",
    )
    parser.add_argument(
        "--serial-slave-framing",
        choices=["rtu", "ascii"],
        help="what the masters on the --serial-slave line speak: rtu "
        "(default; that of --framing when given) or ascii (7E1 unless "
        "--data-bits/--parity)",
    )


#: The argparse type of a flag, by the type of the key it sets.
_ARGUMENT_TYPES: dict[Type, Callable[[str], Any]] = {
    Type.INTEGER: int,
    Type.SECONDS: float,
    Type.NUMBER: float,
    Type.ADDRESS: _host_port,
    Type.ADDRESS_OR_OFF: _metrics_address,
}


def _flag_arguments(key: Key) -> dict[str, Any]:
    """``add_argument`` keywords for the flag of ``key``, from the schema."""
    flag = key.flag
    assert flag is not None
    arguments: dict[str, Any] = {"dest": flag.dest, "help": flag.help}
    if key.type is Type.BOOLEAN:
        return arguments | {"action": "store_true"}
    if flag.repeat:
        arguments["action"] = "append"
    if flag.metavar:
        arguments["metavar"] = flag.metavar
    if flag.choices:
        arguments["choices"] = list(flag.choices)
        numeric = all(isinstance(choice, int) for choice in flag.choices)
        arguments["type"] = int if numeric else str
    else:
        arguments["type"] = _ARGUMENT_TYPES.get(key.type, str)
    return arguments


def _add_run_flags(parser: argparse.ArgumentParser) -> None:
    """How this run behaves: the stop's grace, the demo, the trace."""
    parser.add_argument(
        "--grace",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="how long a stop waits for the transactions on the wire (default 5)",
    )
    parser.add_argument(
        "--demo",
        action="store_true",
        help="serve built-in simulated RTU, ASCII and Modbus TCP slaves (no hardware needed)",
    )
    parser.add_argument(
        "--trace",
        action="store_true",
        help="log every request and reply, decoded, on the gateway.trace logger",
    )
    parser.add_argument(
        "--trace-unit",
        type=int,
        action="append",
        metavar="N",
        help="trace only unit N (repeatable; implies --trace)",
    )
    parser.add_argument(
        "--trace-function",
        type=_function_code,
        action="append",
        metavar="FC",
        help="trace only function FC: 3, 0x10 or read_holding_registers "
        "(repeatable; implies --trace)",
    )
    parser.add_argument("--no-uvloop", action="store_true", help=argparse.SUPPRESS)


def _given(args: argparse.Namespace, scope: Scope) -> dict[Key, Any]:
    """The keys of ``scope`` whose flag was given, with the flag's value."""
    given: dict[Key, Any] = {}
    for key in schema.flagged():
        assert key.flag is not None
        value = getattr(args, key.flag.dest)
        if key.flag.scope is scope and value is not None and value is not False:
            given[key] = list(value) if key.flag.repeat else value
    return given


def apply_overrides(raw: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """Merge command-line flags into the raw configuration tables (the file is not changed)."""
    raw = copy.deepcopy(raw)
    for key, value in _given(args, Scope.TABLE).items():
        raw.setdefault(key.table.value, {})[key.name] = value
    _apply_listener_flags(raw, args)
    lines = raw.setdefault("lines", {})
    _apply_line_sources(lines, args)
    _apply_line_tls_flags(lines, args)
    if args.max_in_flight is not None:
        _apply_max_in_flight(lines, args.max_in_flight)
    every_line = {key.name: value for key, value in _given(args, Scope.EVERY_LINE).items()}
    for table in lines.values():
        if isinstance(table, dict):
            table.update(every_line)
    return raw


def _apply_listener_flags(raw: dict[str, Any], args: argparse.Namespace) -> None:
    """``--tls-*``, ``--rtu-over-tcp-listen`` and ``--serial-slave``: each sets the listener
    named after its protocol (added when the file has none)."""
    tls = {key.name: value for key, value in _given(args, Scope.TLS_LISTENER).items()}
    if tls:
        _set_listener(raw, "tls", tls)
    if args.rtu_over_tcp_listen:
        _set_listener(raw, "rtu-over-tcp", {"listen": args.rtu_over_tcp_listen})
    if args.serial_slave_framing and not args.serial_slave:
        raise ConfigError(
            "--serial-slave-framing", ["it sets the framing of --serial-slave DEVICE: give both"]
        )
    if args.serial_slave:
        serial: dict[str, Any] = {"device": args.serial_slave}
        formats = {
            "baudrate": args.baudrate,
            "data_bits": args.data_bits,
            "parity": args.parity,
            "stop_bits": args.stopbits,
            "framing": args.serial_slave_framing or args.framing,
        }
        serial.update({key: value for key, value in formats.items() if value is not None})
        _set_listener(raw, "serial-slave", serial)


def _apply_line_sources(lines: dict[str, Any], args: argparse.Namespace) -> None:
    """``--serial``, ``--rtu-over-tcp``, ``--modbus-tcp``, ``--modbus-tls``: the one line."""
    if args.serial:
        if not lines:
            lines["default"] = {"device": args.serial, "units": ["1-247"]}
        elif len(lines) == 1:
            next(iter(lines.values()))["device"] = args.serial
        else:
            raise ConfigError(
                "--serial",
                ["the configuration has several lines; set each device in the file instead"],
            )
    if args.rtu_over_tcp:
        _apply_network_line(lines, "rtu-over-tcp", args.rtu_over_tcp, "--rtu-over-tcp", args)
    if args.modbus_tcp:
        if args.rtu_over_tcp:
            raise ConfigError("--modbus-tcp", ["give either --rtu-over-tcp or --modbus-tcp"])
        _apply_network_line(lines, "tcp", args.modbus_tcp, "--modbus-tcp", args)
    if args.modbus_tls:
        if args.rtu_over_tcp or args.modbus_tcp:
            raise ConfigError(
                "--modbus-tls", ["give one of --rtu-over-tcp, --modbus-tcp and --modbus-tls"]
            )
        _apply_network_line(lines, "tls", args.modbus_tls, "--modbus-tls", args)


def _apply_max_in_flight(lines: dict[str, Any], limit: int) -> None:
    """``--max-in-flight N`` for every line framed by MBAP (``tcp``, ``tls``)."""
    tables = [t for t in lines.values() if isinstance(t, dict) and is_mbap(t.get("kind", "rtu"))]
    if not tables:
        problem = "only a Modbus TCP or TLS line takes it: give --modbus-tcp or --modbus-tls"
        raise ConfigError("--max-in-flight", [problem + ", or remove it"])
    for table in tables:
        table["max_in_flight"] = limit


def _apply_network_line(
    lines: dict[str, Any], kind: str, address: str, flag: str, args: argparse.Namespace
) -> None:
    """``--rtu-over-tcp HOST:PORT``: the only line, or the one line of the file, reached there."""
    if args.serial:
        raise ConfigError(flag, ["give either --serial or " + flag + ", not both"])
    if not lines:
        lines["default"] = {"kind": kind, "address": address, "units": ["1-247"]}
    elif len(lines) == 1:
        table = next(iter(lines.values()))
        if isinstance(table, dict):
            table.pop("device", None)
            table.update({"kind": kind, "address": address})
    else:
        raise ConfigError(
            flag, ["the configuration has several lines; set each line's address in the file"]
        )


def _apply_line_tls_flags(lines: dict[str, Any], args: argparse.Namespace) -> None:
    """``--modbus-tls-*`` set the files and server name of every ``kind = "tls"`` line."""
    given = {key: value for key, value in _given(args, Scope.TLS_LINES).items() if value}
    if not given:
        return
    tls_lines = [t for t in lines.values() if isinstance(t, dict) and t.get("kind") == "tls"]
    if not tls_lines:
        flag = next(iter(given)).flag
        assert flag is not None
        problem = 'no line is kind = "tls": give --modbus-tls HOST:PORT, or set the files'
        raise ConfigError(flag.name, [problem + " under the tls line in the file"])
    for table in tls_lines:
        table.update({key.name: value for key, value in given.items()})


def _set_listener(raw: dict[str, Any], protocol: str, values: dict[str, Any]) -> None:
    """Set the listener named ``protocol`` (added when the file has none)."""
    listeners = raw.setdefault("listeners", [])
    if not isinstance(listeners, list):
        return  # build_config reports the type
    entry = next(
        (item for item in listeners if isinstance(item, dict) and item.get("name") == protocol),
        None,
    )
    if entry is None:
        entry = {"name": protocol, "protocol": protocol}
        listeners.append(entry)
    entry.update(values)


def example_config() -> str:
    """The example configuration shipped in the package, every key with its default."""
    return resources.files("gateway").joinpath("data/gateway.example.toml").read_text("utf-8")


def _check_config(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="modbus-gateway check-config", description="Validate a configuration file."
    )
    parser.add_argument("file")
    parser.add_argument(
        "--strict", action="store_true", help="treat warnings as errors (exit 2 on any)"
    )
    args = parser.parse_args(argv)
    try:
        config = build_config(read_config_file(args.file), args.file)
        for listener in config.listeners:
            if listener.tls:
                server_context(listener)  # the files exist, match, and are valid now
        for line in config.lines:
            if line.kind == "tls":
                client_context(line)  # the same for a tls line's client certificate
        if config.metrics.enabled:
            endpoint_tls(config.metrics)  # the same for the HTTP endpoint's HTTPS files
    except ConfigError as error:
        print(error, file=sys.stderr)
        return 2
    except TlsSetupError as error:
        print(f"{args.file}: {error}", file=sys.stderr)
        return 2
    warnings = config_warnings(config) + policy_warnings(config)
    for warning in warnings:
        print(f"{args.file}: warning: {warning}", file=sys.stderr)
    if warnings and args.strict:
        return 2
    listening = ", ".join(
        f"{lst.serial.device} ({lst.name}, {lst.protocol}, {lst.serial.kind})"
        if lst.serial
        else f"{lst.host}:{lst.port} ({lst.name}, {lst.protocol})"
        for lst in config.listeners
    )
    print(
        f"{args.file}: OK: {len(config.lines)} line(s), {len(config.routes)} routed unit(s), "
        f"listening on {listening}" + (f"; {len(warnings)} warning(s)" if warnings else "")
    )
    return 0


def _run(main: Coroutine[Any, Any, None], use_uvloop: bool) -> None:
    if use_uvloop:
        try:
            import uvloop
        except ImportError:
            pass
        else:
            uvloop.run(main)
            return
    asyncio.run(main)


def _file_log_format(raw: dict[str, Any]) -> object:
    table = raw.get("logging")
    return table.get("format") if isinstance(table, dict) else None


def _audit(argv: list[str]) -> int:
    """``audit verify FILE...``: check an audit log's hash chain; 1 names the first bad line."""
    parser = argparse.ArgumentParser(prog="modbus-gateway audit", description=_audit.__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    verify = commands.add_parser("verify", help="check the hash chain of audit log files")
    verify.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="audit log files, oldest first (rotated files in order)",
    )
    args = parser.parse_args(argv)
    from .io.audit import verify_files

    ok, message = verify_files(args.files)
    print(f"modbus-gateway audit verify: {message}", file=sys.stdout if ok else sys.stderr)
    return 0 if ok else 1


def _subcommand(argv: list[str]) -> int | None:
    """Run ``check-config``, ``audit``, ``scan``, ``example-config`` or ``trace --url``."""
    if argv and argv[0] == "check-config":
        return _check_config(argv[1:])
    if argv and argv[0] == "audit":
        return _audit(argv[1:])
    if argv and argv[0] == "scan":
        from .scan import main as scan

        return scan(argv[1:])
    if argv == ["example-config"]:
        sys.stdout.write(example_config())
        return 0
    if argv and argv[0] == "trace" and any(_is_trace_client_flag(arg) for arg in argv[1:]):
        from .trace_client import main as trace_client

        return trace_client(argv[1:])
    return None


def _is_trace_client_flag(arg: str) -> bool:
    """``trace --url`` attaches to a running gateway; ``trace --help`` describes that."""
    return arg in ("--url", "-h", "--help") or arg.startswith("--url=")


def _configure(
    args: argparse.Namespace, json_log: bool
) -> tuple[GatewayConfig, DemoLine | None] | int:
    """The configuration of this run (and the demo's simulated lines), or the exit code."""
    raw: dict[str, Any] = {}
    demo: DemoLine | None = None
    try:
        if args.config:
            raw = read_config_file(args.config)
            if args.log_format is None and _file_log_format(raw) == "json" and not json_log:
                json_log = True
                setup_logging("info", "json")
        if args.demo:
            from .sim.demo import DemoLine

            demo = DemoLine()
            raw = demo.configure(raw, listen=args.listen or DEMO_LISTEN)
        return build_config(apply_overrides(raw, args), args.config or "<command line>"), demo
    except ConfigError as error:
        if json_log:
            log.error("%s", error, extra={"source": error.source, "problems": error.problems})
        else:
            print(f"modbus-gateway: {error}", file=sys.stderr)
        if demo is not None:
            demo.stop()
        return 2


def _reload_source(args: argparse.Namespace) -> Callable[[], Any] | None:
    """What SIGHUP reads: the file with the flags over it, or the flags alone (the TLS
    files they name are read again); the demo does not reload."""
    if args.demo:
        return None
    if args.config:
        return reloader(args.config, lambda raw: apply_overrides(raw, args))

    def from_flags() -> Any:
        return build_config(apply_overrides({}, args), "<command line>")

    return from_flags


def _serve(args: argparse.Namespace, config: GatewayConfig, demo: DemoLine | None) -> int:
    """Run the gateway until a stop signal; the exit code."""
    reload_source = _reload_source(args)

    async def serve() -> None:
        tracer = None
        if args.trace or args.trace_unit or args.trace_function:
            tracer = Tracer(args.trace_unit or (), args.trace_function or ())
        await run_until_signalled(Gateway(config, tracer=tracer), reload_source, args.grace)

    if demo is not None:
        from .sim.demo import DEMO_ASCII_UNITS, DEMO_TCP_UNITS, DEMO_UNITS

        demo.start()
        log.info("demo: simulated units %s on %s", DEMO_UNITS, demo.pty.path)
        log.info("demo: ASCII units %s on %s", DEMO_ASCII_UNITS, demo.ascii_pty.path)
        log.info("demo: Modbus TCP units %s at %s", DEMO_TCP_UNITS, demo.tcp_slave.host_port)
    try:
        _run(serve(), use_uvloop=not args.no_uvloop)
    except DeviceUnusableError as error:
        log.error("cannot start: %s", _device_error(error, args))
        return 1
    except (OSError, TlsSetupError) as error:
        log.error("cannot start: %s", error)
        return 1
    except Exception:  # a bug: still one log record (JSON when asked), then exit 1
        log.critical("stopped by an unexpected error", exc_info=True)
        return 1
    finally:
        if demo is not None:
            demo.stop()
    return 0


def _device_error(error: DeviceUnusableError, args: argparse.Namespace) -> str:
    """The device's error naming the setting as the user gave it: the flag when a flag set
    it (or when no file is in play and a flag exists), else the file's key."""
    if isinstance(error, ListenerDeviceUnusableError):
        if not args.serial_slave or error.line != "serial-slave":
            return str(error)  # a listener of the file: its key there
        if error.key == "device":
            return error.told("--serial-slave")
    elif error.key == "device":
        return error.told("--serial") if args.serial else str(error)
    for key in schema.flagged():  # --baudrate, --data-bits, ... set --serial-slave's too
        flag = key.flag
        if key.table is not Table.LINES or key.name != error.key or flag is None:
            continue
        if not args.config or getattr(args, flag.dest) is not None:
            return error.told(flag.name)
    return str(error)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``modbus-gateway`` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    code = _subcommand(argv)
    if code is not None:
        return code
    if argv and argv[0] == "trace":
        argv = ["--trace", *argv[1:]]
    # Startup errors follow --log-format (or the file's logging.format) too: a JSON log
    # reader (journald, Docker) must not meet a plain-text line when the start fails.
    json_log = _requested_log_format(argv) == "json"
    if json_log:
        setup_logging("info", "json")
    args = build_parser(log_errors=json_log).parse_args(argv)
    configured = _configure(args, json_log)
    if isinstance(configured, int):
        return configured
    config, demo = configured
    setup_logging(config.logging.level, config.logging.format)
    if demo is None:
        for warning in config_warnings(config) + policy_warnings(config):
            log.warning("%s: %s", config.source, warning)
    return _serve(args, config, demo)


if __name__ == "__main__":
    sys.exit(main())
