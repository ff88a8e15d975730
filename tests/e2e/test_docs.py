"""The manual: an MkDocs site in docs/ that builds with ``--strict``, and links that resolve.

The build needs the ``docs`` extra (``pip install -e '.[docs]'``) and is skipped without it;
``.ci/run`` builds the site itself. The link checks need nothing: every relative link in the
README and in the manual's pages reaches a file (and a heading, when it names one), and a
page links only within docs/, since the site holds nothing else.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import tomllib
import unicodedata
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
MKDOCS_YML = REPO / "mkdocs.yml"
README_MAX_LINES = 200
BUILD_TIMEOUT_S = 300.0

_FENCE = re.compile(r"^(```|~~~)")
_CODE_SPAN = re.compile(r"`+[^`]*`+")
_LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def _prose(text: str) -> Iterator[str]:
    """The lines outside fenced code blocks, with inline code spans removed."""
    fenced = False
    for line in text.splitlines():
        if _FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            yield _CODE_SPAN.sub("", line)


def _slug(heading: str) -> str:
    """Python-Markdown's default ``toc`` slug, which MkDocs and GitHub's anchors agree on here."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text only
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def _anchors(page: Path) -> set[str]:
    fenced = False
    found: set[str] = set()
    for line in page.read_text(encoding="utf-8").splitlines():
        if _FENCE.match(line.lstrip()):
            fenced = not fenced
        elif not fenced and (match := _HEADING.match(line)):
            found.add(_slug(match[2]))
    return found


def _links(page: Path) -> Iterator[str]:
    for line in _prose(page.read_text(encoding="utf-8")):
        yield from _LINK.findall(line)


def _pages() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.glob("*.md"))]


def _broken(page: Path, target: str) -> str | None:
    """Why a relative link from ``page`` does not resolve, or ``None`` when it does."""
    path, _, anchor = target.partition("#")
    resolved = (page.parent / path).resolve() if path else page
    if not resolved.exists():
        return "no such file"
    if page.parent == DOCS and not resolved.is_relative_to(DOCS):
        return "outside docs/: the site does not hold it (name the file in code instead)"
    if anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
        return f"no heading #{anchor} in {resolved.relative_to(REPO)}"
    return None


def test_every_relative_link_in_the_readme_and_the_manual_resolves() -> None:
    broken = [
        f"{page.relative_to(REPO)}: ({target}): {why}"
        for page in _pages()
        for target in _links(page)
        if not re.match(r"^[a-z][a-z0-9+.-]*:", target)  # http:, https:, mailto:
        and (why := _broken(page, target)) is not None
    ]
    assert broken == []


def _nav_files(entries: Any) -> Iterator[str]:
    if isinstance(entries, str):
        yield entries
    elif isinstance(entries, list):
        for entry in entries:
            yield from _nav_files(entry)
    elif isinstance(entries, dict):
        for value in entries.values():
            yield from _nav_files(value)


def test_every_page_is_in_the_nav_and_every_nav_entry_exists() -> None:
    config = yaml.safe_load(MKDOCS_YML.read_text(encoding="utf-8"))
    listed = list(_nav_files(config["nav"]))
    assert sorted(listed) == sorted(set(listed)), "a page is listed twice"
    assert set(listed) == {page.name for page in DOCS.glob("*.md")}


def test_the_readme_is_the_front_door() -> None:
    """Under 200 lines; the manual holds the rest."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < README_MAX_LINES, f"README.md has {len(lines)} lines"
    assert any("docs/getting-started.md" in line for line in lines)


def test_the_docs_extra_brings_mkdocs() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    names = {
        re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].lower()
        for requirement in project["optional-dependencies"]["docs"]
    }
    assert {"mkdocs", "mkdocs-material"} <= names


def test_the_manual_builds_strict(tmp_path: Path) -> None:
    """``mkdocs build --strict``: a broken link or anchor, or a page left out, fails it."""
    for module in ("mkdocs", "material"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed: pip install -e '.[docs]'")
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=REPO, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )  # fmt: skip
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-4000:]
    assert (tmp_path / "index.html").is_file()
    assert (tmp_path / "configuration" / "index.html").is_file()


def test_the_getting_started_table_names_every_flag() -> None:
    """Each flag of ``modbus-gateway --help`` has its row in getting-started's table."""
    from gateway.cli import build_parser

    table = "\n".join(
        line
        for line in (DOCS / "getting-started.md").read_text(encoding="utf-8").splitlines()
        if line.startswith("| `-")
    )
    named = set(re.findall(r"`(--[a-z0-9-]+)", table))
    flags = {
        option
        for action in build_parser()._actions
        for option in action.option_strings
        if option.startswith("--") and option != "--help"
    }
    # --no-uvloop is hidden from --help: the benchmark compares the event loops with it.
    assert sorted(flags - named - {"--no-uvloop"}) == []


def test_no_page_quotes_the_old_fixed_timeout() -> None:
    """The automatic timeout is learned; 0.367 s was the fixed default of an earlier version."""
    quoting = [
        f"{page.relative_to(REPO)}:{number}"
        for page in _pages()
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if re.search(r"\b0\.367\b", line)
    ]
    assert quoting == []
