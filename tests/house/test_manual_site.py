"""The built manual (``make docs``, mkdocs into site/) as the service serves it at /guide: the
pages and their assets come from the app and name no other host; /guide says how to build the
manual where it is not built; and the tutorial's page in headless Chromium (tests/browser.py)
shows no console error and draws the theme (checked on the screenshot's pixels).

``make test`` builds the site first (``make docs``); run alone, the :func:`site` fixture builds
it when it is missing.

``FPM_GUIDE_SCREENSHOT=PATH`` also saves the tutorial page's screenshot there.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urlparse

import browser
import httpx
import numpy as np
import pytest
from conftest import stop_process
from fastapi.testclient import TestClient

from service import docs
from service.main import create_app
from stack.redis_server import free_port

ROOT = Path(__file__).resolve().parents[2]
TUTORIAL = "/guide/tutorial/paper-cube/"


@pytest.fixture(scope="module")
def site() -> Path:
    """The built manual (built here with ``mkdocs build --strict`` when it is missing)."""
    if not (docs.SITE / "index.html").is_file():
        subprocess.run(
            [sys.executable, "-m", "mkdocs", "build", "--strict", "-q"],
            cwd=ROOT,
            env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
            check=True,
            timeout=300,
        )
    return docs.SITE


@pytest.fixture(scope="module")
def app_client(site: Path) -> Iterator[TestClient]:
    # No route of /guide touches Redis: the app's default settings will do.
    with TestClient(create_app(), raise_server_exceptions=False) as client:
        yield client


class Loads(HTMLParser):
    """What a page loads (scripts, style sheets, images, frames, fonts) and what it links to."""

    def __init__(self) -> None:
        super().__init__()
        self.loads: list[str] = []
        self.links: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag in ("script", "img", "iframe", "source", "video", "audio") and a.get("src"):
            self.loads.append(a["src"] or "")
        elif tag == "link" and a.get("href"):
            rel = set((a.get("rel") or "").split())
            loaded = rel & {"stylesheet", "icon", "preload", "modulepreload", "manifest"}
            (self.loads if loaded else self.links).append(a["href"] or "")
        elif tag == "a" and a.get("href"):
            self.links.append(a["href"] or "")


def test_the_guide_serves_the_manual_beside_the_api_docs(app_client):
    home = app_client.get("/guide/")
    assert home.status_code == 200 and home.headers["content-type"].startswith("text/html")
    assert "fpm-calibration manual" in home.text
    assert app_client.get("/guide", follow_redirects=False).status_code in (307, 308)
    page = app_client.get(TUTORIAL)
    assert page.status_code == 200 and "examples/paper-material-a.json" in page.text
    for path in ("/guide/reference/spec/", "/guide/reference/rest-api/", "/guide/reference/cli/"):
        assert app_client.get(path).status_code == 200, path
    assert app_client.get("/docs").status_code == 200  # the API's own pages stay
    assert app_client.get("/guide/no-such-page/").status_code == 404


def test_every_page_loads_only_assets_of_the_site(site, app_client):
    """No CDN, no Google Fonts: every script, style sheet, image and font a page loads is one of
    the site's own files, and it is served."""
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 30
    served: set[str] = set()
    for page in pages:
        text = page.read_text()
        assert "fonts.googleapis" not in text and "fonts.gstatic" not in text, page
        parser = Loads()
        parser.feed(text)
        for url in parser.loads:
            parsed = urlparse(url)
            assert not parsed.scheme and not parsed.netloc, (page, url)
            if parsed.path.startswith("/guide/"):  # the 404 page's links are absolute
                target = (site / parsed.path.removeprefix("/guide/")).resolve()
            else:
                target = (page.parent / parsed.path).resolve()
            assert target.is_file() and target.is_relative_to(site.resolve()), (page, url)
            served.add("/guide/" + target.relative_to(site.resolve()).as_posix())
    for css in site.rglob("*.css"):
        assert "@import url(http" not in css.read_text(), css
    for path in sorted(served)[:40]:  # through the app too
        assert app_client.get(path).status_code == 200, path


def test_the_generated_reference_is_the_code(app_client):
    """The reference pages come from the code: a spec field, a route, a CLI option."""
    spec = app_client.get("/guide/reference/spec/").text
    assert "settle_tolerance" in spec and "auto_depth_tolerance" in spec
    rest = app_client.get("/guide/reference/rest-api/").text
    assert "/v1/calibrations" in rest and "submit_calibration" in rest
    cli = app_client.get("/guide/reference/cli/").text
    assert "fpmcal spec from-mesh" in cli and "--spacing" in cli and "fpm-client submit" in cli
    api = app_client.get("/guide/reference/python-api/").text
    assert "load_problem" in api and "Runtime" in api


def test_without_a_built_manual_the_guide_says_how_to_build_it(tmp_path, monkeypatch):
    monkeypatch.setenv("FPM_GUIDE_DIR", str(tmp_path / "nothing-here"))
    client = TestClient(create_app(), raise_server_exceptions=False)
    answer = client.get("/guide/")
    assert answer.status_code == 503 and "make docs" in answer.text
    assert answer.headers["content-type"].startswith("text/html")


@pytest.fixture(scope="module")
def guide_url(site: Path) -> Iterator[str]:
    """The real app under uvicorn (no worker: /guide needs none)."""
    port = free_port()
    api = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "service.main:app", "--port", str(port)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            httpx.get(f"{url}/guide/", timeout=1).raise_for_status()
            break
        except httpx.HTTPError:
            if time.monotonic() > deadline or api.poll() is not None:
                stop_process(api)
                raise RuntimeError("uvicorn did not start") from None
            time.sleep(0.1)
    yield url
    stop_process(api)


def test_the_tutorial_page_in_chromium(guide_url, tmp_path):
    path, why = browser.chromium()
    if path is None:
        pytest.skip(why)
    import matplotlib.pyplot as plt

    with browser.Browser(timeout=60) as page:
        page.open(guide_url + TUTORIAL)
        page.viewport(1280, 900)
        page.wait_for("document.readyState === 'complete' && document.querySelector('h1')")
        page.js("new Promise(done => setTimeout(done, 300))")  # fonts and layout settle
        title = page.js("document.querySelector('.md-content h1').textContent")
        assert "paper" in title.lower()
        assert page.js("document.querySelectorAll('.md-nav__link').length") > 10
        png = page.screenshot(tmp_path / "guide.png")
        errors = page.console_errors()
    assert errors == []
    pixels = (plt.imread(png)[..., :3] * 255).round().astype(np.uint8)
    assert pixels.shape[:2] == (900, 1280), pixels.shape
    # The header bar: the theme's primary colour (blue grey, #546e7a) across the top.
    top = pixels[5:40].reshape(-1, 3).astype(int)
    header = (np.abs(top - [0x54, 0x6E, 0x7A]).sum(axis=1) < 40).mean()
    assert header > 0.5, header
    # The page below it: mostly white paper, with text (dark pixels) on it.
    body = pixels[100:].reshape(-1, 3).astype(int)
    white = (body.min(axis=1) > 245).mean()
    dark = (body.max(axis=1) < 110).mean()
    assert 0.5 < white < 0.99 and dark > 0.005, (white, dark)
    assert browser.distinct_colours(png) > 50
    copy_to = os.environ.get("FPM_GUIDE_SCREENSHOT")
    if copy_to:
        shutil.copyfile(png, copy_to)
