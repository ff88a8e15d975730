"""TLS under the systemd unit: keys handed over by ``LoadCredential=`` (the TLS drop-in).

No systemd runs the service here, so the test does what systemd does for it: it copies each
``LoadCredential=`` file into a credentials directory readable only by the service's user,
sets ``CREDENTIALS_DIRECTORY``, expands ``%d`` and ``%i`` in the drop-in's ``ExecStart=``,
and runs that command line (as ``nobody`` when the test runs as root, like the unit's
transient user, with the original keys out of its reach). Then the manual's pymodbus TLS
example (docs/listeners-and-security.md) reads registers through it.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.e2e.test_startup_messages import Started
from tests.helpers import DEADLINE_S, require_tool

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "conf" / "modbus-gateway@.service"
DROP_IN = REPO / "conf" / "modbus-gateway-tls.conf"
INSTALLED_EXEC = "/usr/local/bin/modbus-gateway"
NOBODY = 65534


def _directives(text: str, name: str) -> list[str]:
    return [line.partition("=")[2] for line in text.splitlines() if line.startswith(f"{name}=")]


def _docs_block(marker: str, language: str) -> str:
    """The first ``language`` block after ``marker`` in the manual's security page."""
    text = (REPO / "docs" / "listeners-and-security.md").read_text(encoding="utf-8")
    after = text[text.index(marker) :]
    start = after.index(f"```{language}\n") + len(f"```{language}\n")
    return after[start : after.index("```", start)]


@pytest.fixture
def service_dir() -> Iterator[Path]:
    """A directory the service's user can reach (pytest's own is private to root)."""
    directory = Path(tempfile.mkdtemp(prefix="modbus-gateway-service-"))
    directory.chmod(0o755)
    yield directory
    shutil.rmtree(directory)


def _load_credentials(sources: Path, credentials: Path, drop_in: str, as_root: bool) -> None:
    """What systemd does for ``LoadCredential=ID:PATH``: a private copy of PATH named ID."""
    credentials.mkdir(mode=0o500)
    for entry in _directives(drop_in, "LoadCredential"):
        name, _, path = entry.partition(":")
        assert path.startswith("/etc/modbus-gateway/tls/"), entry
        copy = credentials / name
        shutil.copyfile(sources / Path(path).name, copy)
        copy.chmod(0o400)
        if as_root:
            os.chown(copy, NOBODY, NOBODY)
    if as_root:
        os.chown(credentials, NOBODY, NOBODY)


def _exec_start(drop_in: str, credentials: Path, config: Path) -> list[str]:
    """The drop-in's ``ExecStart=``, expanded as systemd expands it for instance ``plant``."""
    *reset, command = _directives(drop_in, "ExecStart")
    assert reset == [""], "the drop-in must reset the unit's ExecStart first"
    command = command.replace("%d", str(credentials)).replace("%i", "plant")
    words = shlex.split(command.replace("/etc/modbus-gateway/plant.toml", str(config)))
    assert words[0] == INSTALLED_EXEC
    return words[1:]


def test_tls_keys_reach_the_gateway_through_load_credential(
    tmp_path: Path, service_dir: Path
) -> None:
    require_tool("openssl")
    made = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", _docs_block("<!-- tls-setup -->", "sh")],
        cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    tls = tmp_path / "tls"  # root's keys, chmod 600: out of the service user's reach
    as_root = os.geteuid() == 0
    drop_in = DROP_IN.read_text(encoding="utf-8")
    credentials = service_dir / "credentials"
    _load_credentials(tls, credentials, drop_in, as_root)
    config = service_dir / "plant.toml"
    config.write_text(  # the file still names the originals: the flags must win
        '[[listeners]]\nname = "tls"\nprotocol = "tls"\nlisten = "127.0.0.1:0"\n'
        'cert = "/etc/modbus-gateway/tls/server.pem"\nkey = "/etc/modbus-gateway/tls/server.key"\n'
        'ca = "/etc/modbus-gateway/tls/ca.pem"\n'
    )
    config.chmod(0o644)
    args = _exec_start(drop_in, credentials, config)
    prefix: tuple[str, ...] = ()
    if as_root:
        prefix = (require_tool("setpriv"), f"--reuid={NOBODY}", f"--regid={NOBODY}",
                  "--clear-groups")  # fmt: skip
    gateway = Started(*args, "--demo", "--listen", "127.0.0.1:0", "--metrics", "off",
                      prefix=prefix, env={"CREDENTIALS_DIRECTORY": str(credentials)})  # fmt: skip
    try:
        port = gateway.wait_for(r"listening on 127\.0\.0\.1:(\d+) \(Modbus/TCP Security\)")[1]
        example = _docs_block("<!-- tls-python -->", "python")
        assert "port=8802" in example
        read = subprocess.run(
            [sys.executable, "-c", example.replace("port=8802", f"port={port}")],
            cwd=tmp_path, capture_output=True, text=True, timeout=DEADLINE_S * 3, check=False,
        )  # fmt: skip
        assert read.returncode == 0, read.stderr
        assert re.fullmatch(r"\[(\d+, ){9}\d+\]\n", read.stdout), read.stdout
    finally:
        assert gateway.stop() == 0, gateway.log


def test_the_unit_with_the_tls_drop_in_verifies(tmp_path: Path) -> None:
    """``systemd-analyze verify`` reads the drop-in too, beside the unit's own directives."""
    analyze = require_tool("systemd-analyze")
    executable = shutil.which("modbus-gateway") or str(Path(sys.executable).with_name(
        "modbus-gateway"))  # fmt: skip
    if not Path(executable).exists():
        pytest.skip("the modbus-gateway command is not installed (pip install -e .)")
    instance = tmp_path / "modbus-gateway@plant.service"
    instance.write_text(UNIT.read_text(encoding="utf-8").replace(INSTALLED_EXEC, executable))
    drop_ins = tmp_path / "modbus-gateway@plant.service.d"
    drop_ins.mkdir()
    (drop_ins / "tls.conf").write_text(
        DROP_IN.read_text(encoding="utf-8").replace(INSTALLED_EXEC, executable)
    )
    done = subprocess.run(
        [analyze, "verify", "--man=no", instance.name], cwd=tmp_path,
        env=dict(os.environ, SYSTEMD_UNIT_PATH=f"{tmp_path}:"),
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    ours = [line for line in done.stderr.splitlines() if "modbus-gateway" in line]
    assert done.returncode == 0 and not ours, done.stderr
