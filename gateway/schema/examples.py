"""Example blocks of the example configuration: listeners, rules, line kinds, routes.

Each body is real TOML: the example file shows it commented out (except the route), and
tests/unit/test_schema.py loads every body, so an example never names a key the parser
refuses.
"""

from __future__ import annotations

from dataclasses import dataclass

from .keys import LINES
from .model import Table

_CACHE_HELP = next(key.help for key in LINES if key.name == "cache")


@dataclass(frozen=True)
class Example:
    """A block of the example file, written after the keys of ``after``."""

    after: Table
    intro: str
    body: str
    commented: bool = True


EXAMPLES = (
    Example(
        Table.SERVER,
        'More listeners: protocol "tcp" (Modbus TCP), "tls" (Modbus/TCP Security: TLS 1.2 or '
        "newer, client certificates required, the role from the certificate's extension "
        '1.3.6.1.4.1.50316.802.1), "rtu-over-tcp" (masters sending bare RTU frames over TCP: '
        'one request at a time per connection, answered in order) or "serial-slave" (below). '
        "Each takes read_only and policy as above; the network ones take allow too. "
        "conf/gateway.locked-down.toml is a complete example.",
        """\
[[listeners]]
name = "tls"
protocol = "tls"
listen = "0.0.0.0:802"
cert = "/etc/modbus-gateway/tls/server.pem"   # the server's chain, leaf first
key = "/etc/modbus-gateway/tls/server.key"
ca = "/etc/modbus-gateway/tls/ca.pem"         # client certificates must chain to these
policy = "plant"
[[listeners]]
name = "rtu"
protocol = "rtu-over-tcp"
listen = "0.0.0.0:4001"
""",
    ),
    Example(
        Table.SERVER,
        "Reverse mode: the gateway answers RTU (or ASCII) masters on a serial line of its own "
        "as the slaves it routes (silent for other units, damaged frames and broadcasts, "
        "answers after a turnaround: t3.5 for RTU, one character for ASCII); units limits it.",
        """\
[[listeners]]
name = "field"
protocol = "serial-slave"
device = "/dev/ttyUSB1"
baudrate = 9600
parity = "N"
data_bits = 8
stop_bits = 1
units = [1, "10-20"]
framing = "rtu"          # or "ascii": ':' to CR LF with LRC, 7E1 unless data_bits/parity;
                         # then inter_char_timeout = 1.0 drops a frame whose characters
                         # stop this long
echo = false             # true: the adapter hears its own answers; they are dropped
""",
    ),
    Example(
        Table.SERVER,
        "Rules only grant: a request is served when one rule matching the master (role, "
        "source) grants its unit, function, access and whole address range; everything else "
        'gets 0x01. Omitted keys mean "any"; units omitted never include broadcast (unit 0).',
        """\
[[policies.plant.rules]]
role = "operator"                 # and/or source = "10.1.2.0/24"
units = ["1-10"]
functions = ["read_holding_registers", 6, 16]   # FC 8 by subfunction: "8:0"
addresses = ["0-999"]
access = "read_write"             # "read", "write" or "read_write"
""",
    ),
    Example(
        Table.LINES,
        _CACHE_HELP,
        """\
[[lines.a.cache]]
unit = 1
function = 3
start = 0
count = 100
max_age = 0.5
""",
    ),
    Example(
        Table.LINES,
        "A second line:",
        """\
[lines.b]
device = "/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A10K1ABC-if00-port0"
baudrate = 19200
parity = "E"
units = [20, 21]
""",
    ),
    Example(
        Table.LINES,
        'A serial device server (Moxa NPort "TCP server" mode and the like) reached over TCP:',
        """\
[lines.net]
kind = "rtu-over-tcp"
address = "10.0.0.5:4001"   # the device server's data port; replaces device
baudrate = 19200            # its serial side: sets the automatic timeout (+ 0.1 s network)
frame_gap = 0           # default 0: the device server keeps t3.5 on its serial side
silence = 0.05          # quiet time ending an answer of unknown length (a user code)
connect_timeout = 3     # seconds a connection attempt may take
connect_delay = 0       # seconds the line stays down (0x0A) after connecting
units = [30, 31]
""",
    ),
    Example(
        Table.LINES,
        'A Modbus/TCP Security slave (docs/line-kinds.md, "Modbus/TCP Security slaves"): '
        'the frames of a "tcp" line over TLS 1.2 or newer, with the gateway\'s client '
        "certificate. The slave's certificate must chain to ca and carry server_name; "
        "check_server_name = false skips the name only (warned).",
        """\
[lines.plc7]
kind = "tls"
address = "plc-7.plant.example"   # port 802 when none is given
cert = "/etc/modbus-gateway/tls/gateway.pem"   # the gateway's client chain, leaf first
key = "/etc/modbus-gateway/tls/gateway.key"    # its private key (unencrypted PEM)
ca = "/etc/modbus-gateway/tls/plant-ca.pem"    # CAs the slave's certificate must chain to
server_name = "plc-7.plant.example"   # default: the address's host
check_server_name = true
tls_handshake_timeout = 10.0   # seconds; the line stays down (0x0A) while it fails
timeout = 0.5
units = [70]
""",
    ),
    Example(
        Table.LINES,
        "A Modbus TCP slave (TCP-to-TCP proxying), MBAP under the gateway's own transaction ids:",
        """\
[lines.plc]
kind = "tcp"
address = "10.0.0.20:502"
max_in_flight = 1       # requests outstanding at once on the connection (1..64; MBAP lines
                        # only). Many devices take one at a time: raise it only for those
                        # that answer several. One master's requests to one unit keep
                        # read-after-write order (docs/line-kinds.md).
units = [40]
""",
    ),
    Example(
        Table.ROUTES,
        'Remapping: TCP unit 100 goes to slave 1 on line "a". Unit 255 (the gateway itself, '
        "per the TCP implementation guide) answers 0x0A unless routed here.",
        """\
[[routes]]
unit = 100
line = "a"
slave = 1
""",
        commented=False,
    ),
    Example(
        Table.POLLING,
        "A poll block: the gateway reads 50 holding registers of unit 1 every second and "
        "answers masters' reads inside them from memory, never with data older than max_age. "
        "Writes go through and the block is read again before it serves reads again.",
        """\
[[poll]]
unit = 1          # the unit id masters use (routed as any request)
function = 3      # 1, 2, 3 or 4
address = 0
count = 50        # at most 125 registers, 2000 bits
every = 1.0       # seconds between polls
max_age = 3.0     # never answered from memory with older data; default 3 x every
""",
    ),
)
