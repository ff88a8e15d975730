"""Line kinds in the configuration: ``rtu`` (a serial device), ``rtu-over-tcp`` (over TCP)."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.cli import apply_overrides, build_parser
from gateway.config import ConfigError, auto_timeout, build_config, config_warnings
from gateway.core.timing import t35
from tests.helpers import problems


def test_an_rtu_over_tcp_line_and_its_network_defaults() -> None:
    config = build_config(
        {"lines": {"net": {"kind": "rtu-over-tcp", "address": "10.0.0.5:4001", "units": [1]}}}
    )
    line = config.line("net")
    assert (line.kind, line.host, line.port, line.device) == (
        "rtu-over-tcp", "10.0.0.5", 4001, "10.0.0.5:4001",
    )  # fmt: skip
    assert line.networked and line.is_url
    assert line.gap == 0.0  # the device server keeps t3.5 on its serial side
    assert line.silence == 0.05  # segments and device-server buffering, not t3.5
    assert line.timeout == round(auto_timeout(9600) + 0.1, 3)
    assert (line.connect_delay, line.connect_timeout) == (0.0, 3.0)
    assert config_warnings(config) == []  # no "device does not exist" for an address


def test_rtu_over_tcp_settings_override_the_defaults() -> None:
    table = {"kind": "rtu-over-tcp", "address": "[fd00::5]:4001", "units": [1], "frame_gap": 0.005,
             "silence": 0.2, "connect_delay": 0.5, "connect_timeout": 1, "timeout": 1}  # fmt: skip
    line = build_config({"lines": {"net": table}}).line("net")
    assert (line.host, line.port, line.device) == ("fd00::5", 4001, "[fd00::5]:4001")
    assert (line.gap, line.silence, line.connect_delay, line.connect_timeout, line.timeout) == (
        0.005, 0.2, 0.5, 1.0, 1.0,
    )  # fmt: skip


def test_a_serial_line_keeps_t35_and_may_set_its_silence() -> None:
    line = build_config({"lines": {"a": {"device": "/dev/ttyS0", "units": [1]}}}).line("a")
    assert (line.kind, line.networked, line.gap, line.silence) == (
        "rtu", False, t35(9600), t35(9600),
    )  # fmt: skip
    table = {"device": "/dev/ttyS0", "units": [1], "silence": 0.01}
    assert build_config({"lines": {"a": table}}).line("a").silence == 0.01


@pytest.mark.parametrize(
    ("table", "expected"),
    [
        ({"kind": "rtu-over-tcp", "units": [1]},
         "lines.n.address: missing; a rtu-over-tcp line needs the device server's address, "
         'like "10.0.0.5:4001"'),
        ({"kind": "rtu-over-tcp", "address": "10.0.0.5", "units": [1]},
         "lines.n.address: '10.0.0.5' is not HOST:PORT; write it like 0.0.0.0:502"),
        ({"kind": "rtu-over-tcp", "address": "0.0.0.0:4001", "units": [1]},
         "lines.n.address: '0.0.0.0:4001' is not a place to connect to; write the device "
         'server\'s address, like "10.0.0.5:4001"'),
        ({"kind": "rtu-over-tcp", "device": "/dev/ttyUSB0", "address": "h:1", "units": [1]},
         'lines.n.device: a rtu-over-tcp line is reached at address = "HOST:PORT", not a device; '
         "rename the key to address"),
        ({"device": "/dev/ttyUSB0", "address": "h:1", "units": [1]},
         'lines.n.address: only a network line takes it (kind = "rtu-over-tcp", "tcp" or '
         '"tls"); a rtu line names its serial port with device'),
        ({"kind": "rtu-over-udp", "device": "/dev/ttyUSB0", "units": [1]},
         "lines.n.kind: 'rtu-over-udp' is not one of: rtu, ascii, rtu-over-tcp, tcp, tls"),
    ],
)  # fmt: skip
def test_mistakes_name_the_key_and_the_fix(table: dict[str, Any], expected: str) -> None:
    assert problems({"lines": {"n": table}}) == [expected]


def test_two_lines_on_one_device_server_is_an_error() -> None:
    lines = {name: {"kind": "rtu-over-tcp", "address": "10.0.0.5:4001", "units": [unit]}
             for name, unit in (("a", 1), ("b", 2))}  # fmt: skip
    assert problems({"lines": lines}) == [
        "lines.b.device: '10.0.0.5:4001' is the device of line 'a' too; one serial device "
        "serves one line: merge the two lines' units into lines.a"
    ]


def test_the_rtu_over_tcp_flag() -> None:
    args = build_parser().parse_args(["--rtu-over-tcp", "10.0.0.5:4001"])
    line = build_config(apply_overrides({}, args)).line("default")
    assert (line.kind, line.device, line.gap) == ("rtu-over-tcp", "10.0.0.5:4001", 0.0)
    assert len(build_config(apply_overrides({}, args)).routes) == 247
    # One line in the file: it becomes the network line, keeping its other settings.
    raw = {"lines": {"a": {"device": "/dev/ttyUSB0", "units": [3], "retries": 2}}}
    line = build_config(apply_overrides(raw, args)).line("a")
    assert (line.kind, line.device, line.retries) == ("rtu-over-tcp", "10.0.0.5:4001", 2)
    both = build_parser().parse_args(["--rtu-over-tcp", "h:1", "--serial", "/dev/ttyS0"])
    with pytest.raises(ConfigError, match="either --serial or --rtu-over-tcp"):
        apply_overrides({}, both)


def test_the_rtu_over_tcp_listener_flag_and_table() -> None:
    args = build_parser().parse_args(["--serial", "/dev/ttyS0", "--rtu-over-tcp-listen", ":4001"])
    config = build_config(apply_overrides({}, args))
    (listener,) = config.listeners  # alone: as with --tls-listen, no implicit tcp listener
    assert (listener.name, listener.protocol, listener.host, listener.port) == (
        "rtu-over-tcp", "rtu-over-tcp", "0.0.0.0", 4001,
    )  # fmt: skip
    entry = {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "0.0.0.0:4001", "cert": "a.pem"}
    found = problems({"lines": {"a": {"device": "/dev/ttyS0"}}, "listeners": [entry]})
    assert found == ['listeners[0].cert: only a protocol = "tls" listener takes it']


def test_a_serial_slave_listener_and_its_flag() -> None:
    args = build_parser().parse_args(
        ["--serial", "/dev/ttyS0", "--serial-slave", "/dev/ttyS1", "--baudrate", "19200"]
    )
    config = build_config(apply_overrides({}, args))
    tcp, slave = config.listeners  # the tcp listener stays: a serial-slave does not replace it
    assert (tcp.protocol, slave.name, slave.protocol) == ("tcp", "serial-slave", "serial-slave")
    assert slave.serial is not None
    assert (slave.serial.device, slave.serial.baudrate, slave.units) == ("/dev/ttyS1", 19200, ())


def test_an_ascii_serial_slave_listener_is_7e1_by_default() -> None:
    entry: dict[str, Any] = {"protocol": "serial-slave", "device": "/dev/ttyS1", "framing": "ascii"}
    config = build_config({"lines": {"a": {"device": "/dev/ttyS0"}}, "listeners": [entry]})
    serial = config.listeners[-1].serial
    assert serial is not None
    assert (serial.kind, serial.data_bits, serial.parity, serial.stop_bits) == ("ascii", 7, "E", 1)
    assert (serial.inter_char_timeout, serial.echo) == (1.0, False)
    entry.update(data_bits=8, parity="N", inter_char_timeout=0.5, echo=True)
    config = build_config({"lines": {"a": {"device": "/dev/ttyS0"}}, "listeners": [entry]})
    serial = config.listeners[-1].serial
    assert serial is not None
    assert (serial.data_bits, serial.parity, serial.inter_char_timeout, serial.echo) == (
        8, "N", 0.5, True,
    )  # fmt: skip
    plain = {"protocol": "serial-slave", "device": "/dev/ttyS1"}
    rtu = build_config({"lines": {"a": {"device": "/dev/ttyS0"}}, "listeners": [plain]})
    serial = rtu.listeners[-1].serial
    assert serial is not None
    assert (serial.kind, serial.data_bits, serial.parity) == ("rtu", 8, "N")


def test_the_serial_slave_framing_flags() -> None:
    def slave_of(*argv: str) -> Any:
        args = build_parser().parse_args(["--serial", "/dev/ttyS0", "--serial-slave", "/dev/ttyS1",
                                          *argv])  # fmt: skip
        return build_config(apply_overrides({}, args)).listeners[-1].serial

    ascii_slave = slave_of("--serial-slave-framing", "ascii", "--data-bits", "8", "--parity", "N")
    assert (ascii_slave.kind, ascii_slave.data_bits, ascii_slave.parity) == ("ascii", 8, "N")
    assert slave_of("--framing", "ascii").kind == "ascii"  # --framing applies to it too
    both = slave_of("--framing", "ascii", "--serial-slave-framing", "rtu")
    assert (both.kind, both.data_bits, both.parity) == ("rtu", 8, "N")  # its own framing's format
    assert slave_of().kind == "rtu"
    args = build_parser().parse_args(["--serial", "/dev/ttyS0", "--serial-slave-framing", "ascii"])
    with pytest.raises(ConfigError) as caught:
        apply_overrides({}, args)
    assert str(caught.value).startswith("--serial-slave-framing: ")
    assert caught.value.problems == ["it sets the framing of --serial-slave DEVICE: give both"]


@pytest.mark.parametrize(
    ("entry", "expected"),
    [
        ({"protocol": "serial-slave"},
         'listeners[0].device: missing; a serial-slave listener answers on a serial device, '
         'like "/dev/ttyUSB1" (or --serial-slave DEVICE)'),
        ({"protocol": "serial-slave", "device": "/dev/ttyS0"},
         "listeners[0].device: '/dev/ttyS0' is the device of line 'a' too; a serial-slave "
         "listener needs a serial line of its own"),
        ({"protocol": "serial-slave", "device": "/dev/ttyS1", "listen": "0.0.0.0:1"},
         "listeners[0].listen: a serial-slave listener has a device, not an address"),
        ({"protocol": "tcp", "listen": "0.0.0.0:1", "baudrate": 9600},
         'listeners[0].baudrate: only a protocol = "serial-slave" listener takes it'),
        ({"protocol": "serial-slave", "device": "/dev/ttyS1", "units": [0]},
         "listeners[0].units: unit 0 outside 1..247 (0 is broadcast, 248..255 are reserved)"),
        ({"protocol": "serial-slave", "device": "/dev/ttyS1", "framing": "tcp"},
         "listeners[0].framing: 'tcp' is not one of: rtu, ascii"),
        ({"protocol": "serial-slave", "device": "/dev/ttyS1", "inter_char_timeout": 0.5},
         'listeners[0].inter_char_timeout: only an ASCII line has one (framing = "ascii"); '
         "an RTU frame ends on t3.5 of silence"),
        ({"protocol": "serial-slave", "device": "/dev/ttyS1", "echo": "yes"},
         "listeners[0].echo: 'yes' is not true or false"),
        ({"protocol": "tcp", "listen": "0.0.0.0:1", "framing": "ascii"},
         'listeners[0].framing: only a protocol = "serial-slave" listener takes it'),
    ],
)  # fmt: skip
def test_serial_slave_mistakes(entry: dict[str, Any], expected: str) -> None:
    raw = {"lines": {"a": {"device": "/dev/ttyS0", "units": [1]}}, "listeners": [entry]}
    assert problems(raw) == [expected]
