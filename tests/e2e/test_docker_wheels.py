"""docker/wheels/README.md: its wheel list is all an offline image build needs.

The list is downloaded exactly as the README says (``--no-deps``: nothing comes in
unnamed), then the gateway is built and installed from it alone, with ``--no-index``,
in a fresh venv, as the Dockerfile's builder stage does: compiled where this machine has a
C compiler and the Python headers (the build requirements come from the list, through build
isolation), pure Python otherwise. Needs a reachable package index.
"""

from __future__ import annotations

import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
WHEELS_README = REPO / "docker" / "wheels" / "README.md"
PIP_TIMEOUT_S = 900

#: The download, then mypyc and the C compiler on a busy machine.
pytestmark = pytest.mark.timeout(1800)


def _download_command() -> list[str]:
    """The README's ``pip download`` command, as words."""
    text = WHEELS_README.read_text(encoding="utf-8")
    after = text[text.index("<!-- offline-wheels -->") :]
    start = after.index("```sh\n") + len("```sh\n")
    block = after[start : after.index("\n```", start)]
    joined = block.replace("\\\n", " ")
    (command,) = [line for line in joined.splitlines() if "pip download" in line]
    return shlex.split(command)


def _name(requirement: str) -> str:
    """``'uvloop>=0.17; sys_platform != "win32"'`` → ``uvloop``."""
    match = re.match(r"[A-Za-z0-9._-]+", requirement)
    assert match, requirement
    return match[0].lower().replace("_", "-")


def test_the_list_names_the_backend_and_every_runtime_dependency() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    wanted = {_name(r) for r in project["build-system"]["requires"]}
    wanted |= {_name(r) for r in project["project"]["dependencies"]}
    named = {_name(word) for word in _download_command() if not word.startswith("-")}
    assert wanted <= named, f"missing from docker/wheels/README.md: {sorted(wanted - named)}"


def _offline_environment() -> dict[str, str]:
    """No pip configuration: a site's ``find-links`` or extra index must not fill a gap."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "PYTHONPATH"))}
    return env | {"PIP_CONFIG_FILE": os.devnull}


def _run(*command: str, env: dict[str, str] | None = None) -> str:
    done = subprocess.run(
        command, env=env, capture_output=True, text=True, timeout=PIP_TIMEOUT_S, check=False
    )
    assert done.returncode == 0, f"{shlex.join(command)}\n{done.stdout}\n{done.stderr}"
    return done.stdout


def _expected_build() -> str:
    """``compiled`` where a C compiler and the Python headers exist, else ``interpreted``."""
    compiler = (sysconfig.get_config_var("CC") or "cc").split()[0]
    headers = Path(sysconfig.get_paths()["include"]) / "Python.h"
    return "compiled" if shutil.which(compiler) and headers.is_file() else "interpreted"


def test_the_gateway_builds_and_installs_from_that_list_alone(tmp_path: Path) -> None:
    if platform.machine() != "x86_64" or sys.version_info[:2] != (3, 11):
        pytest.skip("the README's list is for CPython 3.11 on x86_64")
    command = _download_command()
    assert command[:3] == ["python3", "-m", "pip"] and "--no-deps" in command
    wheels = tmp_path / "wheels"
    command[command.index("--dest") + 1] = str(wheels)
    try:
        _run(sys.executable, *command[1:], "--disable-pip-version-check")
    except AssertionError as error:
        if "Could not fetch URL" in str(error) or "NewConnectionError" in str(error):
            pytest.skip(f"no package index reachable: {error}")
        raise
    env = tmp_path / "venv"
    venv.create(env, with_pip=True)
    pip = [str(env / "bin" / "python"), "-m", "pip", "--disable-pip-version-check"]
    offline = ["--no-index", "--find-links", str(wheels)]
    dist = tmp_path / "dist"
    # The Dockerfile's builder: the project's wheel in build isolation (the backend from
    # the list), then the project and its dependencies from the list alone.
    alone = _offline_environment()
    source = tmp_path / "source"  # what the Dockerfile copies; a build leaves files behind
    source.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, source / name)
    shutil.copytree(REPO / "gateway", source / "gateway",
                    ignore=shutil.ignore_patterns("__pycache__", "*.so"))  # fmt: skip
    _run(*pip, "wheel", *offline, "--no-deps", "--wheel-dir", str(dist), str(source), env=alone)
    (project,) = dist.glob("modbus_gateway-*.whl")
    _run(*pip, "install", *offline, str(project), env=alone)
    # The venv's gateway, not a checkout's on PYTHONPATH or in the working directory.
    version = _run(
        str(env / "bin" / "modbus-gateway"), "--version", env=alone | {"PYTHONSAFEPATH": "1"}
    )
    assert version.startswith("modbus-gateway "), version
    assert version.strip().endswith(f"({_expected_build()})"), version
    _run(str(env / "bin" / "python"), "-c", "import cryptography.x509, serial, uvloop")
