"""``kind = "tls"`` lines: their keys, defaults, mistakes, flags and client TLS context."""

from __future__ import annotations

import datetime as dt
import ssl
from pathlib import Path
from typing import Any

import pytest

from gateway.cli import apply_overrides, build_parser
from gateway.config import ConfigError, LineConfig, build_config, config_warnings
from gateway.core.framing import LineKind, framing_for
from gateway.io.links.tls import (
    LineTlsFailure,
    client_context,
    line_failure_message,
    line_failure_reason,
)
from gateway.io.tls_setup import TlsSetupError
from gateway.sim.pki import Pki
from tests.helpers import problems


def files(pki: Pki, client: str = "operator") -> dict[str, str]:
    cert, key = pki.client(client)
    return {"cert": cert, "key": key, "ca": str(pki.ca)}


def tls_line(pki: Pki, **options: Any) -> LineConfig:
    table: dict[str, Any] = {"kind": "tls", "address": "10.0.0.7:802", "units": [1]}
    table.update(files(pki))
    table.update(options)
    return build_config({"lines": {"plc": table}}).line("plc")


def test_a_tls_line_and_its_defaults(pki: Pki) -> None:
    line = tls_line(pki)
    assert (line.kind, line.host, line.port) == ("tls", "10.0.0.7", 802)
    assert line.device == "10.0.0.7:802"
    assert line.networked and line.gap == 0.0 and line.silence == 0.05
    assert line.server_name == "10.0.0.7" and line.check_server_name
    assert line.tls_handshake_timeout == 10.0
    assert line.timeout == pytest.approx(0.467)  # a network line's auto timeout, as for tcp
    assert framing_for(line.kind).kind is LineKind.TCP  # the MBAP framing itself


@pytest.mark.parametrize(
    ("address", "expected"),
    [("plc-7.plant.example", ("plc-7.plant.example", 802)), ("[fd00::7]", ("fd00::7", 802)),
     ("10.0.0.7:8802", ("10.0.0.7", 8802)), ("[fd00::7]:8802", ("fd00::7", 8802))],
)  # fmt: skip
def test_a_missing_port_is_802(pki: Pki, address: str, expected: tuple[str, int]) -> None:
    line = tls_line(pki, address=address)
    assert (line.host, line.port) == expected
    assert line.server_name == expected[0]


def test_settings_override_the_defaults(pki: Pki) -> None:
    line = tls_line(pki, server_name="plc-7.plant.example", tls_handshake_timeout=2.5,
                    check_server_name=False)  # fmt: skip
    assert (line.server_name, line.tls_handshake_timeout) == ("plc-7.plant.example", 2.5)
    assert not line.check_server_name


@pytest.mark.parametrize(
    ("table", "expected"),
    [
        ({"kind": "tls", "address": "h:802", "key": "k", "ca": "c"},
         "lines.plc.cert: missing; a tls line needs the gateway's client certificate chain"),
        ({"kind": "tls", "address": "h:802", "cert": "c", "ca": "c"},
         "lines.plc.key: missing; a tls line needs the private key of that certificate"),
        ({"kind": "tls", "address": "h:802", "cert": "c", "key": "k"},
         "(or --modbus-tls-ca FILE)"),
        ({"kind": "tls", "address": "h:802", "cert": 5, "key": "k", "ca": "c"},
         "lines.plc.cert: write a file path as a string"),
        ({"kind": "tls", "address": "h:802", "cert": "c", "key": "k", "ca": "c", "server_name": 7},
         "lines.plc.server_name: write the name the slave's certificate carries"),
        ({"kind": "tls", "address": "h:802", "cert": "c", "key": "k", "ca": "c",
          "server_name": "plc 7"}, "lines.plc.server_name: 'plc 7' is not a host name"),
        ({"kind": "tls", "address": "h:802", "cert": "c", "key": "k", "ca": "c",
          "server_name": "a..b"}, "lines.plc.server_name: 'a..b' is not a host name"),
        ({"kind": "tcp", "address": "h:502", "cert": "c"},
         'lines.plc.cert: only a kind = "tls" line takes it'),
        ({"device": "/dev/ttyS0", "server_name": "x"},
         'lines.plc.server_name: only a kind = "tls" line takes it'),
        ({"kind": "tls", "cert": "c", "key": "k", "ca": "c"}, "lines.plc.address: missing"),
    ],
)  # fmt: skip
def test_mistakes_name_the_key_and_the_fix(table: dict[str, Any], expected: str) -> None:
    assert expected in "\n".join(problems({"lines": {"plc": {"units": [1], **table}}}))


def test_skipping_the_name_check_is_warned_about(pki: Pki) -> None:
    table = {"kind": "tls", "address": "10.0.0.7", "units": [1], **files(pki)}
    config = build_config({"lines": {"plc": {**table, "check_server_name": False}}})
    (warning,) = [w for w in config_warnings(config) if "check_server_name" in w]
    assert "must still chain to lines.plc.ca" in warning
    assert not [w for w in config_warnings(build_config({"lines": {"plc": table}}))
                if "check_server_name" in w]  # fmt: skip


def test_the_modbus_tls_flags(pki: Pki) -> None:
    cert, key = pki.client("operator")
    args = build_parser().parse_args([
        "--modbus-tls", "plc-7.plant.example", "--modbus-tls-cert", cert, "--modbus-tls-key",
        key, "--modbus-tls-ca", str(pki.ca), "--modbus-tls-server-name", "plc-7",
    ])  # fmt: skip
    config = build_config(apply_overrides({}, args))
    line = config.line("default")
    assert (line.kind, line.device, line.server_name) == ("tls", "plc-7.plant.example:802", "plc-7")
    assert (line.cert, line.key, line.ca) == (cert, key, str(pki.ca))
    assert len(config.routes) == 247
    # The file's tls line takes the flags too.
    raw = {"lines": {"a": {"kind": "tls", "address": "h", "cert": "x", "key": "y", "ca": "z"}}}
    args = build_parser().parse_args(["--modbus-tls-cert", cert])
    assert build_config(apply_overrides(raw, args)).line("a").cert == cert


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--modbus-tls-ca", "ca.pem"], 'no line is kind = "tls"'),
        (["--modbus-tls", "h", "--modbus-tcp", "h:502"], "give one of --rtu-over-tcp"),
        (["--modbus-tls", "h", "--serial", "/dev/ttyS0"], "give either --serial or --modbus-tls"),
    ],
)
def test_flag_mistakes(argv: list[str], expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        apply_overrides({}, build_parser().parse_args(argv))


def test_the_client_context(pki: Pki) -> None:
    built = client_context(tls_line(pki))
    context = built.context
    assert context.minimum_version is ssl.TLSVersion.TLSv1_2
    assert context.verify_mode is ssl.CERT_REQUIRED and context.check_hostname
    unchecked = client_context(tls_line(pki, check_server_name=False)).context
    assert unchecked.verify_mode is ssl.CERT_REQUIRED and not unchecked.check_hostname
    found = [(info.listener, info.kind, info.subject) for info in built.certificates]
    assert found == [("plc", "client", "master-operator"), ("plc", "chain", "Test Intermediate CA"),
                     ("plc", "ca", "Test Root CA")]  # fmt: skip
    assert 364 * 86400 < built.certificates[0].seconds_left() <= 365 * 86400


def test_client_context_mistakes_name_the_key_the_file_and_the_fix(
    pki: Pki, tmp_path: Path
) -> None:
    missing = str(tmp_path / "nothing.pem")
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.cert = '.*nothing\.pem': cannot read"):
        client_context(tls_line(pki, cert=missing))
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.ca = '.*nothing\.pem': cannot read"):
        client_context(tls_line(pki, ca=missing))
    garbage = tmp_path / "garbage.key"
    garbage.write_text("not a key\n")
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.key = .*garbage\.key.*unencrypted PEM"):
        client_context(tls_line(pki, key=str(garbage)))
    other_key = pki.client("viewer")[1]
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.key = .*viewer\.key'?: cannot be used "
                       r"with lines\.plc\.cert"):  # fmt: skip
        client_context(tls_line(pki, key=other_key))
    expired_cert, expired_key = pki.client("expired")
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.cert = .*expired on .*renew it"):
        client_context(tls_line(pki, cert=expired_cert, key=expired_key))
    not_pem = tmp_path / "ca.txt"
    not_pem.write_text("hello\n")
    with pytest.raises(TlsSetupError, match=r"lines\.plc\.ca = .*no PEM certificate"):
        client_context(tls_line(pki, ca=str(not_pem)))


def test_failure_reasons_and_their_messages(pki: Pki) -> None:
    def verify_error(code: int, message: str) -> ssl.SSLCertVerificationError:
        error = ssl.SSLCertVerificationError(1, message)
        error.verify_code, error.verify_message = code, message
        return error

    line = tls_line(pki)
    cases = [
        (verify_error(62, "Hostname mismatch"), LineTlsFailure.NAME_MISMATCH, "server_name"),
        (verify_error(64, "IP address mismatch"), LineTlsFailure.NAME_MISMATCH, "server_name"),
        (verify_error(10, "certificate has expired"), LineTlsFailure.EXPIRED_CERTIFICATE, "renew"),
        (verify_error(20, "unable to get local issuer certificate"),
         LineTlsFailure.UNTRUSTED_CERTIFICATE, "lines.plc.ca"),
        (TimeoutError("no complete TLS handshake in time"), LineTlsFailure.TIMEOUT,
         "lines.plc.tls_handshake_timeout"),
        (ConnectionResetError(104, "reset"), LineTlsFailure.CLOSED, "may refuse"),
    ]  # fmt: skip
    for error, reason, fix in cases:
        assert line_failure_reason(error) is reason
        assert fix in line_failure_message(line, reason, error)
    assert 'kind = "tcp"' in line_failure_message(line, LineTlsFailure.NOT_TLS, OSError("x"))
    assert "TLS 1.2" in line_failure_message(line, LineTlsFailure.PROTOCOL_VERSION, OSError("x"))


def test_a_client_certificate_not_yet_valid(pki: Pki) -> None:
    line = tls_line(pki)
    earlier = dt.datetime.now(dt.UTC) - dt.timedelta(days=3)
    with pytest.raises(TlsSetupError, match="is not valid before"):
        client_context(line, now=earlier)
