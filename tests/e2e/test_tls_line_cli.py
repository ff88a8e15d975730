"""``kind = "tls"`` lines through the real command: check-config, a failed start, the flags.

The line's TLS files are checked before anything opens: a key that does not match its
certificate, or an expired client certificate, names the key, the file and the fix.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from gateway.sim.pki import Pki

TIMEOUT_S = 30


def tls_config(tmp_path: Path, pki: Pki, key: str | None = None, **extra: str) -> Path:
    cert, own_key = pki.client("operator")
    lines = [
        "[lines.plc]", 'kind = "tls"', 'address = "127.0.0.1"', f'cert = "{cert}"',
        f'key = "{key or own_key}"', f'ca = "{pki.ca}"', "units = [7]",
    ]  # fmt: skip
    lines += [f"{name} = {value}" for name, value in extra.items()]
    path = tmp_path / "gateway.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *argv], capture_output=True, text=True,
        timeout=TIMEOUT_S, check=False,
    )  # fmt: skip


def test_check_config_reads_a_tls_lines_files(tmp_path: Path, pki: Pki) -> None:
    checked = run("check-config", str(tls_config(tmp_path, pki)))
    assert checked.returncode == 0, checked.stderr
    unchecked = run("check-config", str(tls_config(tmp_path, pki, check_server_name="false")))
    assert unchecked.returncode == 0, unchecked.stderr
    assert "lines.plc.check_server_name: false" in unchecked.stderr
    wrong_key = pki.client("viewer")[1]
    broken = run("check-config", str(tls_config(tmp_path, pki, key=wrong_key)))
    assert broken.returncode == 2
    assert f"lines.plc.key = '{wrong_key}': cannot be used with lines.plc.cert" in broken.stderr


def test_an_expired_client_certificate_stops_the_start(tmp_path: Path, pki: Pki) -> None:
    cert, key = pki.client("expired")
    started = run(
        "--modbus-tls", "127.0.0.1", "--modbus-tls-cert", cert, "--modbus-tls-key", key,
        "--modbus-tls-ca", str(pki.ca), "--listen", "127.0.0.1:0", "--metrics", "off",
    )  # fmt: skip
    assert started.returncode == 1
    assert f"lines.default.cert = '{cert}': the client certificate" in started.stderr
    assert "expired on" in started.stderr and "renew it" in started.stderr


def test_modbus_tls_flags_without_a_tls_line(tmp_path: Path, pki: Pki) -> None:
    started = run("--serial", "/dev/null", "--modbus-tls-ca", str(pki.ca))
    assert started.returncode == 2
    assert 'no line is kind = "tls"' in started.stderr
