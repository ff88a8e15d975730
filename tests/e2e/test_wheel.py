"""The wheel: it installs the ``modbus-gateway`` command and carries the example configuration."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.helpers import environment_with_our_dependencies

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A wheel built from this checkout (no network: the build backend is already installed);
    pure Python, as tests/e2e/test_compiled.py builds and tests the compiled one."""
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(ROOT)],
        env={**os.environ, "MODBUS_GATEWAY_COMPILE": "0"}, check=True, timeout=120,
    )  # fmt: skip
    (built,) = out.glob("modbus_gateway-*.whl")
    return built


def test_the_wheel_carries_the_example_configuration(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        example = archive.read("gateway/data/gateway.example.toml").decode()
    assert "gateway/py.typed" in names
    assert example == (ROOT / "conf" / "gateway.example.toml").read_text()
    assert not any(name.startswith(("tests/", "bench/")) for name in names)


def test_the_installed_command(wheel: Path, tmp_path: Path) -> None:
    """Installed into a fresh environment (dependencies from this one), the command runs."""
    env_dir = tmp_path / "venv"
    python = environment_with_our_dependencies(env_dir, wheel)
    imported = subprocess.run(
        [python, "-c", "import gateway; print(gateway.__file__)"],
        capture_output=True, text=True, check=True, cwd=tmp_path,
    ).stdout.strip()  # fmt: skip
    assert Path(imported).is_relative_to(env_dir), f"not the wheel's copy: {imported}"
    command = env_dir / "bin" / "modbus-gateway"
    version = subprocess.run(
        [command, "--version"], capture_output=True, text=True, check=True, cwd=tmp_path
    )
    assert version.stdout.strip().startswith("modbus-gateway ")
    example = subprocess.run(
        [command, "example-config"], capture_output=True, text=True, check=True, cwd=tmp_path
    ).stdout
    config = tmp_path / "gateway.toml"
    config.write_text(example)
    checked = subprocess.run(
        [command, "check-config", str(config)],
        capture_output=True, text=True, check=True, cwd=tmp_path,
    )  # fmt: skip
    assert "OK" in checked.stdout
