"""The manual's shell blocks run as written, in a fresh copy of the checkout and a fresh venv.

Every ```sh block of the README and of docs/ is either run here or marked, on the line above
its fence, ``<!-- example: REASON -->``: a block that needs hardware, root, a container
engine or names of the reader's own. The blocks run page by page, in the order a reader
meets them (README, index, getting started, then the rest by name), each with bash
``-euo pipefail`` in the copy's top directory, with ``.venv/bin`` first on ``PATH`` as
getting-started tells the reader to set it up. So they install what they say (``pip install
.`` compiles, as a user's does), from the package index.

- A line that starts the gateway itself (``modbus-gateway --demo ...``, the end of the
  README's install line) runs in the background as a second shell would, until the page's
  blocks are done; it must then stop on SIGTERM with exit 0 and no ERROR in its log.
- The README's test command is run up to its ``pytest``, which is what ``.ci/run`` runs
  verbatim (``tests/e2e/test_packaging.py`` checks they agree).
- A comment that quotes text (``# "Verification: OK"``) names output the block must print.
- A command already run (the README's install, repeated on getting-started) runs once.
"""

from __future__ import annotations

import enum
import os
import queue
import re
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import release, require_tool

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
#: Pages in the order a reader meets them.
FIRST_PAGES = ("README.md", "docs/index.md", "docs/getting-started.md")
EXAMPLE = re.compile(r"^\s*<!-- example: (?P<reason>\S.*?) -->\s*$")
FENCE = re.compile(r"^(?P<indent>\s*)```(?P<lang>[\w-]*)\s*$")
SHELL = frozenset({"sh", "bash", "shell"})
#: The gateway serving (not a subcommand that ends by itself).
SERVER = re.compile(
    r"^(?:\S*/)?modbus-gateway\s+(?!check-config|example-config|scan|audit|trace|--version)"
)
TEST_COMMAND = re.compile(r"^(?P<install>.+) && (?P<venv>\S+)/bin/python -m pytest -q$")
EXPECTED = re.compile(r'\s#\s[^\n]*?"(?P<text>[^"]+)"')
READY = re.compile(r"listening on [\d.]+:\d+")
#: Installs compile the gateway (about two minutes on two idle cores, more when shared).
SCRIPT_TIMEOUT_S = 1200.0
SERVER_READY_S = 60.0
SERVER_STOP_S = 30.0

pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]


@dataclass(frozen=True)
class Block:
    """One fenced shell block of a page."""

    page: str
    line: int
    text: str
    example: str | None  #: the reason it is not run, or None

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def _pages() -> list[str]:
    rest = sorted(f"docs/{page.name}" for page in DOCS.glob("*.md"))
    return [*FIRST_PAGES, *(page for page in rest if page not in FIRST_PAGES)]


def shell_blocks() -> list[Block]:
    """Every shell block of the README and the manual, in reading order."""
    found: list[Block] = []
    for page in _pages():
        lines = (REPO / page).read_text(encoding="utf-8").splitlines()
        index = 0
        while index < len(lines):
            fence = FENCE.match(lines[index])
            if fence is None:
                index += 1
                continue
            end = index + 1
            while not re.match(rf"^{fence['indent']}```\s*$", lines[end]):
                end += 1
            if fence["lang"] in SHELL:
                indent = len(fence["indent"])
                text = "\n".join(line[indent:] for line in lines[index + 1 : end])
                above = next((line for line in reversed(lines[:index]) if line.strip()), "")
                marked = EXAMPLE.match(above)
                found.append(Block(page, index + 1, text, marked["reason"] if marked else None))
            index = end + 1
    return found


def _logical_lines(text: str) -> list[str]:
    """Lines with their backslash continuations joined (a server line is one of them)."""
    return text.replace("\\\n", " ").splitlines()


def _without_comment(line: str) -> str:
    return re.sub(r"(^|\s+)#\s.*$", "", line).strip()


def _commands(script: str) -> tuple[str, ...]:
    """What a script runs, comments and blank lines aside: the same install on two pages is
    one command."""
    return tuple(filter(None, (_without_comment(line) for line in _logical_lines(script))))


class StepKind(enum.Enum):
    """How a piece of a block runs."""

    SCRIPT = "script"  #: in the foreground, to its end
    SERVER = "server"  #: the gateway, in the background until the page is done
    LEFT_TO_CI = "left to .ci/run"  #: the README's pytest, which .ci/run runs verbatim


@dataclass(frozen=True)
class Step:
    """What running a block comes to: scripts in the foreground, servers in the background."""

    kind: StepKind
    text: str


def steps(block: Block) -> Iterator[Step]:
    """The block cut at the lines that start the gateway: scripts, servers, and the README's
    test command's pytest (left to .ci/run)."""
    script: list[str] = []
    for line in _logical_lines(block.text):
        command = _without_comment(line)
        parts = command.split(" && ")
        tested = TEST_COMMAND.match(command)
        if SERVER.match(parts[-1]):
            if parts[:-1]:
                script.append(" && ".join(parts[:-1]))
            if script:
                yield Step(StepKind.SCRIPT, "\n".join(script))
                script = []
            yield Step(StepKind.SERVER, parts[-1])
        elif tested is not None:
            script.append(tested["install"])
            yield Step(StepKind.SCRIPT, "\n".join(script))
            script = []
            yield Step(StepKind.LEFT_TO_CI, command)
        else:
            script.append(line)
    if any(_without_comment(line) for line in script):
        yield Step(StepKind.SCRIPT, "\n".join(script))


class Server:
    """A gateway a block started, as a reader's second shell would hold it."""

    def __init__(self, command: str, cwd: Path, env: dict[str, str]) -> None:
        self.command = command
        self.process = subprocess.Popen(
            ["bash", "-c", f"exec {command}"], cwd=cwd, env=env, stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.log: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.lines.put(line)
        self.lines.put(None)

    def wait_ready(self) -> None:
        deadline = time.monotonic() + SERVER_READY_S
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=remaining)
            except queue.Empty:
                break
            if line is None:
                break
            self.log.append(line)
            if READY.search(line):
                # The start-up lines after it (the other listeners, the HTTP endpoint).
                return
        raise AssertionError(f"{self.command!r} did not start:\n{''.join(self.log)}")

    def stop(self) -> tuple[int, str]:
        """SIGTERM; the exit code and the whole log."""
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(SERVER_STOP_S)
        self._reader.join(SERVER_STOP_S)
        while (line := self.lines.get_nowait() if not self.lines.empty() else None) is not None:
            self.log.append(line)
        release(self.process)
        return code, "".join(self.log)

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        release(self.process)


def _checkout(into: Path) -> Path:
    """A copy of the checkout's files as a fresh clone has them (no venv, no build)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    copy = into / "modbus-gateway"
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            target = copy / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    return copy


def _environment(checkout: Path) -> dict[str, str]:
    """The reader's shell: the venv's bin/ first on PATH (getting-started), nothing of ours."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "VIRTUAL_ENV", "MODBUS_GATEWAY_COMPILE")}  # fmt: skip
    env["PATH"] = f"{checkout / '.venv' / 'bin'}:{env.get('PATH', '/usr/bin:/bin')}"
    return env


def _run_script(text: str, cwd: Path, env: dict[str, str], where: str) -> str:
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", text], cwd=cwd, env=env, stdin=subprocess.DEVNULL,
        capture_output=True, text=True, timeout=SCRIPT_TIMEOUT_S, check=False,
    )  # fmt: skip
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"{where}: exit {done.returncode}\n{text}\n{output[-6000:]}"
    for expected in EXPECTED.finditer(text):
        assert expected["text"] in output, f"{where}: no {expected['text']!r} in\n{output}"
    return output


def test_every_block_is_run_or_an_example_with_a_reason() -> None:
    """Static: a block that needs what this machine lacks says so, and only such a block."""
    needs = re.compile(r"/dev/ttyUSB|\bsudo\b|\bdocker\b|GATEWAY_IP|\$\w*TOKEN|plant\.example")
    for block in shell_blocks():
        if block.example is None:
            assert not needs.search(block.text), f"{block.where}: mark it as an example"
        else:
            assert len(block.example) > 10, f"{block.where}: say why it is not run"


def test_the_manuals_shell_blocks_run_as_written(
    tmp_path: Path, record_property: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    for tool in ("mbpoll", "openssl", "jq", "gcc"):
        require_tool(tool)
    checkout = _checkout(tmp_path)
    env = _environment(checkout)
    done: set[tuple[str, ...]] = set()
    left_to_ci: set[str] = set()
    ran, examples = 0, 0
    blocks = shell_blocks()
    for page in dict.fromkeys(block.page for block in blocks):
        servers: list[Server] = []
        try:
            for block in (b for b in blocks if b.page == page):
                if block.example is not None:
                    examples += 1
                    continue
                ran += 1
                for step in steps(block):
                    if step.kind is StepKind.LEFT_TO_CI:
                        left_to_ci.add(step.text)
                    elif step.kind is StepKind.SERVER:
                        server = Server(step.text, checkout, env)
                        servers.append(server)
                        server.wait_ready()
                    elif (key := _commands(step.text)) not in done:
                        _run_script(step.text, checkout, env, block.where)
                        done.add(key)
            while servers:
                server = servers.pop()
                code, log = server.stop()
                assert code == 0, f"{page}: {server.command!r} exited {code}:\n{log}"
                assert " ERROR " not in log and "Traceback" not in log, log
        finally:
            for server in servers:
                server.kill()
    record_property("manual_blocks_run", ran)
    record_property("manual_blocks_examples", examples)
    with capsys.disabled():
        print(f"\nmanual: {ran} shell blocks run ({len(done)} distinct scripts; "
              f"{len(left_to_ci)} pytest command left to .ci/run), "
              f"{examples} examples")  # fmt: skip
