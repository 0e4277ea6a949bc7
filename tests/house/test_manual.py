"""Every code block of the manual's tutorial and how-to guides runs, page by page, as a reader
would run it.

A page's blocks run in order in one fresh working directory (with ``examples/`` linked in), like
a notebook: ``python`` blocks share one namespace per page, ``sh`` blocks run with ``bash -e``
and the project's ``.venv/bin`` first on PATH. A ``text`` block right after a code block and
marked ``<!-- output -->`` must be exactly what that block printed (stdout, trailing spaces
aside). A block preceded by ``<!-- not run: REASON -->`` is only shown (e.g. ``docker compose``
on several hosts); REASON is required, and those blocks are listed in the test's report.
Other languages (``json``, ``text``, ``yaml``) are shown, not run. ``FPM_MANUAL_TIMES=1`` (with
``-s``) prints each block's seconds.

The tutorial's three parts run in order in one directory, as one test against the service.
How-to pages that talk to the service (``<!-- manual: service -->`` on the page) run against
the test stack of tests/conftest.py (:func:`live_api`: uvicorn and one worker on the session's
redis-server): the default address ``http://127.0.0.1:8000`` in their blocks is replaced by the
test stack's, and ``REDIS_URL`` points at its Redis.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TUTORIAL = [
    ROOT / "docs" / "tutorial" / f"{name}.md"
    for name in ("paper-cube", "organ-mesh", "view-and-engine")
]
"""The tutorial's parts, in order: they run one after the other in one directory (part 3 uses
what part 2 made)."""
HOWTOS = sorted((ROOT / "docs" / "howto").glob("*.md"))
PAGES = TUTORIAL + HOWTOS
RUN = {"python", "sh"}
SHOWN = {"json", "text", "yaml", "console", "toml", "xml"}
DEFAULT_URL = "http://127.0.0.1:8000"
FENCE = re.compile(r"^```(\S*)[^\n]*\n(.*?)^```\s*$", re.S | re.M)
NOT_RUN = re.compile(r"<!--\s*not run:\s*(.*?)\s*-->\s*$", re.S)


@dataclass
class Block:
    language: str
    code: str
    line: int
    not_run: str | None  # the reason, for a block that is only shown
    output: bool  # a text block marked <!-- output -->: the block before it prints this


def blocks(page: Path) -> list[Block]:
    text = page.read_text()
    found = []
    for match in FENCE.finditer(text):
        before = text[: match.start()].rstrip()
        reason = NOT_RUN.search(before[-300:])
        found.append(
            Block(
                language=match.group(1),
                code=match.group(2),
                line=text.count("\n", 0, match.start()) + 1,
                not_run=reason.group(1) if reason else None,
                output=before.endswith("<!-- output -->"),
            )
        )
    return found


def test_every_block_is_run_or_says_why_not():
    assert PAGES, "no tutorial or how-to pages"
    for page in PAGES:
        for block in blocks(page):
            where = f"{page.relative_to(ROOT)}:{block.line}"
            assert block.language in RUN | SHOWN, f"{where}: unknown language {block.language!r}"
            if block.not_run is not None:
                assert len(block.not_run) > 10, f"{where}: say why the block is not run"
            if block.output:
                assert block.language == "text", f"{where}: an output block is ```text"


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def run_page(page: Path, workdir: Path, url: str | None, redis_url: str | None) -> list[str]:
    """Run the page's blocks; the blocks not run, with their reasons."""
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(ROOT),
        "COLUMNS": "100",
    }
    if redis_url:
        env["REDIS_URL"] = redis_url
    namespace: dict[str, object] = {"__name__": "__manual__"}
    printed = ""
    skipped = []
    for block in blocks(page):
        where = f"{page.relative_to(ROOT)}:{block.line}"
        code = block.code.replace(DEFAULT_URL, url) if url else block.code
        if block.output:
            expected = "\n".join(line.rstrip() for line in block.code.strip().splitlines())
            got = "\n".join(line.rstrip() for line in printed.strip().splitlines())
            assert got == expected, f"{where}: the block before printed\n{printed}"
            continue
        if block.not_run is not None:
            skipped.append(f"{where}: {block.not_run}")
            continue
        started = time.perf_counter()
        if block.language == "python":
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                try:
                    exec(compile(code, where, "exec"), namespace)
                except Exception as error:
                    raise AssertionError(f"{where}: {error!r}\n{out.getvalue()}") from error
            printed = out.getvalue()
        elif block.language == "sh":
            done = subprocess.run(
                ["bash", "-e", "-o", "pipefail", "-c", code],
                cwd=workdir,
                env=env,
                capture_output=True,
                text=True,
                timeout=300,
            )
            assert done.returncode == 0, f"{where}: exit {done.returncode}\n{done.stderr}"
            printed = done.stdout
        if os.environ.get("FPM_MANUAL_TIMES"):  # which blocks cost the test's time
            print(f"{where}: {time.perf_counter() - started:.1f} s", file=sys.stderr)
    return skipped


def needs_service(page: Path) -> bool:
    return "<!-- manual: service -->" in page.read_text()


def test_the_tutorial_lists_every_part():
    assert sorted(TUTORIAL) == sorted((ROOT / "docs" / "tutorial").glob("*.md"))


@pytest.mark.redis
def test_the_tutorial_runs(workdir, live_api, redis_server):
    for page in TUTORIAL:
        run_page(page, workdir, live_api, redis_server.url.replace("/0", "/1"))


@pytest.mark.parametrize("page", [p for p in HOWTOS if not needs_service(p)], ids=lambda p: p.stem)
def test_howto_runs(page, workdir):
    run_page(page, workdir, None, None)


@pytest.mark.redis
@pytest.mark.parametrize("page", [p for p in HOWTOS if needs_service(p)], ids=lambda p: p.stem)
def test_howto_runs_against_the_service(page, workdir, live_api, redis_server):
    run_page(page, workdir, live_api, redis_server.url.replace("/0", "/1"))
