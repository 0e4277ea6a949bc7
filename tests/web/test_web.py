"""The web view: the page and its assets (no CDN), the profile plot's JSON, and the page in a real
browser (headless Chromium, installed from Debian's package when missing: tests/browser.py)
against the live stack with a finished calibration, and the cancel button with API keys set.

``FPM_WEB_SCREENSHOT=docs/web-view.png`` also saves the calibration page's screenshot there
(the README's picture).
"""

from __future__ import annotations

import copy
import html
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browser
import httpx
import numpy as np
import pytest
from conftest import SMALL_SPEC, stop_process
from fastapi.testclient import TestClient
from pydantic import SecretStr
from test_service import assert_problem

from service.main import create_app
from stack.redis_server import free_port
from store import graph, keys

pytestmark = pytest.mark.redis

STATIC = Path(__file__).resolve().parents[2] / "service" / "static" / "web"
TERMINAL = ("succeeded", "failed", "canceled")
TAB_BLUE, TAB_ORANGE = (0x1F, 0x77, 0xB4), (0xFF, 0x7F, 0x0E)
"""The first two chart colours (matplotlib's, as in the CLI plot)."""


def pct(value: float) -> str:
    """A percentage as the page writes it (2 decimals)."""
    return f"{value:.2f}%"


def js_num(value: float) -> str:
    """A number as the page's num() writes it (4 significant digits, no trailing .0)."""
    text = repr(float(f"{value:.4g}"))
    return text[:-2] if text.endswith(".0") else text


def text_of(markup: str) -> str:
    """The visible text of an HTML fragment, whitespace collapsed."""
    markup = re.sub(r"<(script|style)\b.*?</\1>", " ", markup, flags=re.S)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", markup)).split())


def element(dom: str, tag: str, attribute: str) -> str:
    """The first ``<tag ATTRIBUTE ...>...</tag>`` of ``dom`` (no nesting of the same tag)."""
    start = dom.index(f"<{tag} {attribute}")
    return dom[start : dom.index(f"</{tag}>", start)]


# --- In-process: what is served, and the profile JSON --------------------------------------------


def test_page_and_assets_need_no_key_and_load_nothing_from_elsewhere(settings, redis):
    secured = settings.model_copy(update={"api_keys": [SecretStr("s3cret")]})
    client = TestClient(create_app(secured), raise_server_exceptions=False)
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert 'src="web/app.js"' in page.text and 'href="web/style.css"' in page.text
    script, style = client.get("/web/app.js"), client.get("/web/style.css")
    assert script.status_code == style.status_code == 200
    assert "javascript" in script.headers["content-type"]
    assert style.headers["content-type"].startswith("text/css")
    for text in (page.text, script.text, style.text):
        assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text)
        assert not re.search(r"""url\(\s*["']?(https?:)?//""", text)
        assert "@import" not in text and "<iframe" not in text
    # The one absolute URL in the script is the SVG namespace, which loads nothing.
    assert re.findall(r"https?://[^\s\"'`]+", script.text) == ["http://www.w3.org/2000/svg"]
    assert "innerHTML" not in script.text  # text from the service is inserted as text
    assert_problem(client.get("/v1/calibrations/0123456789abcdef/profile"), 401)
    assert client.get("/web/nothing.js").status_code == 404
    paths = client.get("/openapi.json").json()["paths"]
    assert "/" not in paths
    operation = paths["/v1/calibrations/{calibration_id}/profile"]["get"]
    assert operation["operationId"] == "get_calibration_profile"
    assert {"200", "202", "401", "404", "409", "503"} <= set(operation["responses"])


def test_profile_of_a_calibration(api, redis, run_workers, small_spec):
    calibration = api.post("/v1/calibrations", json=small_spec).json()
    path = f"/v1/calibrations/{calibration['id']}/profile"
    assert "no current result" in assert_problem(api.get(path), 409)["detail"]
    run_workers()
    first = api.get(path)
    assert first.status_code == 202 and first.json()["status"] == "pending"
    assert api.get(path).status_code == 202
    assert graph.queue(redis).count == 1  # one job however often it is asked
    run_workers()
    answer = api.get(path)
    assert answer.status_code == 200
    data = answer.json()
    assert data["status"] == "ready" and data["error"] is None
    done = api.get(f"/v1/calibrations/{calibration['id']}").json()
    result = done["result"]
    fem = api.get(f"/v1/fem-references/{done['fem_reference_id']}").json()
    assert [c["name"] for c in data["load_cases"]] == fem["load_cases"] == ["0.05 N", "0.1 N"]
    assert data["h"] == pytest.approx(result["h"])
    nodes = np.array(fem["nodes"])
    for j, case in enumerate(data["load_cases"]):
        line = case["nodes"]
        axis = "xyz".index(case["axis"])
        others = [a for a in range(3) if a != axis]
        assert case["force_axis"] == "z" and axis != 2  # across the loaded face, as in the plot
        assert len(line) == 4 and case["position"] == sorted(case["position"])
        assert case["position"] == nodes[line, axis].tolist()
        assert np.allclose(nodes[line][:, others], nodes[line[0], others])  # one straight line
        assert any(np.allclose(nodes[i], [0.01, 0.01, 0.03]) for i in line)  # the loaded node
        q = np.linalg.norm(np.array(fem["displacements"][j])[line], axis=1)
        assert np.allclose(case["fem"], q)
        for name in ("relative_discrepancy", "loaded_discrepancy", "discrepancy_h"):
            assert case[name] == result[name][j], name
        assert case["settled"] and case["steps"] == result["settle_steps"][j]
        fpm = np.array(case["fpm"])
        assert np.all(fpm > 0) and np.abs(fpm - q).sum() < 0.5 * q.sum()
    assert graph.queue(redis).count == 0 and api.get(path).json() == data  # stored: no new job

    # A profile that cannot be computed says why (and is not re-run at every poll).
    redis.delete(f"{keys.calibration(calibration['id'])}:profile")
    redis.delete(keys.fem_reference(done["fem_reference_id"]))
    assert api.get(path).status_code == 202
    run_workers()
    failed = api.get(path).json()
    assert failed["status"] == "failed" and "no longer stored" in failed["error"]
    assert_problem(api.get("/v1/calibrations/0123456789abcdef/profile"), 404)
    assert_problem(api.get("/v1/calibrations/nope/profile"), 404)


# --- In a real browser, against the live stack ----------------------------------------------------


@pytest.fixture(scope="module")
def chromium() -> str:
    """A headless Chromium (installed with apt-get when missing), or a skip saying why not."""
    path, why = browser.chromium()
    if path is None:
        pytest.skip(f"no headless browser for the web view's tests: {why}")
    return path


def wait_for(what: str, get: Any, done: Any, timeout: float = 120) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = get()
        if done(value):
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: still {value}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def finished(live_api: str, chromium: str) -> dict[str, Any]:
    """One finished small calibration on the live stack, its profile computed, its records."""
    spec = copy.deepcopy(SMALL_SPEC)
    spec["name"] = "web view box"
    with httpx.Client(base_url=live_api, timeout=10) as http:
        submitted = http.post("/v1/calibrations", json=spec).json()
        path = f"/v1/calibrations/{submitted['id']}"
        calibration = wait_for(
            "calibration", lambda: http.get(path).json(), lambda c: c["status"] in TERMINAL
        )
        assert calibration["status"] == "succeeded", calibration
        wait_for(
            "profile",
            lambda: http.get(f"{path}/profile").json(),
            lambda p: p["status"] != "pending",
            timeout=60,
        )
        parameter_set = http.get(f"/v1/parameter-sets/{calibration['parameter_set_id']}").json()
        fem = http.get(
            f"/v1/fem-references/{calibration['fem_reference_id']}", params={"arrays": False}
        ).json()
    return {
        "url": live_api,
        "calibration": calibration,
        "parameter_set": parameter_set,
        "names": fem["load_cases"],
    }


def test_browser_lists_the_calibration_with_status_and_figures(finished):
    c = finished["calibration"]
    dom = browser.dump_dom(f"{finished['url']}/")
    row = text_of(element(dom, "tr", f'data-id="{c["id"]}"'))
    assert "web view box" in row and c["id"] in row and "succeeded" in row and "done" in row
    assert " / ".join(pct(v) for v in c["result"]["relative_discrepancy"]) in row
    total = c["progress"]["total_iterations"]
    assert f"{total} / {total} moves" in row


def test_browser_shows_a_calibration_with_its_charts(finished, tmp_path):
    c, ps, names = finished["calibration"], finished["parameter_set"], finished["names"]
    r = c["result"]
    url = f"{finished['url']}/#/calibrations/{c['id']}"
    dom = browser.dump_dom(url)
    text = text_of(dom)
    assert "web view box" in text and c["id"] in text and "succeeded" in text
    fit = text_of(element(dom, "div", 'class="panel" id="fit"'))
    for j, name in enumerate(names):  # relative first, loaded nodes and % of h beside it
        figures = [pct(r["relative_discrepancy"][j]), pct(r["loaded_discrepancy"][j])]
        assert f"{name} {' '.join(figures)} {pct(r['discrepancy_h'][j])}" in fit
    params = text_of(element(dom, "div", 'class="panel" id="parameters"'))
    assert f"{js_num(r['k'])} N/m" in params
    assert c["parameter_set_id"] == ps["id"] and ps["id"] in params
    assert f"{js_num(r['d'])} N s/m" in params
    assert f"{r['depth']} layers (the deepest perturbed list: {r['full_depth']})" in params
    # The profile chart: FEM and FPM lines per load case, the relative figure in the legend.
    for j, name in enumerate(names):
        assert re.search(f'data-series="FEM {re.escape(name)} \\(along [xy]\\)"', dom)
        relative, of_h = pct(r["relative_discrepancy"][j]), pct(r["discrepancy_h"][j])
        assert f'data-series="FPM: {relative} relative, {of_h} of h"' in dom
    history = element(dom, "div", 'class="panel" id="history"')
    assert history.count('<path d="M') == 2  # current state and best so far
    assert 'data-series="current state"' in history

    png = browser.screenshot(url, tmp_path / "calibration.png", size=(1280, 1560))
    colours = browser.distinct_colours(png)
    assert colours > 50, f"a nearly blank screenshot: {colours} colours"
    import matplotlib.pyplot as plt

    pixels = (plt.imread(png)[..., :3] * 255).round().astype(int).reshape(-1, 3)
    for colour in (TAB_BLUE, TAB_ORANGE):  # the charts were drawn
        assert (np.abs(pixels - colour).sum(axis=1) <= 6).sum() > 200, colour
    copy_to = os.environ.get("FPM_WEB_SCREENSHOT")
    if copy_to:
        shutil.copyfile(png, copy_to)


def test_browser_draws_the_jobs_on_their_workers(finished, tmp_path):
    """The timeline panel: a bar per job of the result (the critical path's outlined), its
    figures in the text, and the load cases' green bars on the screenshot."""
    c = finished["calibration"]
    r = c["result"]
    url = f"{finished['url']}/#/calibrations/{c['id']}"
    dom = browser.dump_dom(url)
    panel = element(dom, "div", 'class="panel" id="timeline"')
    assert f"{len(r['jobs'])} jobs on 1 worker(s)" in text_of(panel)
    assert " → ".join(r["critical_path"]) in html.unescape(text_of(panel))
    for job in r["jobs"]:
        assert f'data-job="{html.escape(job["name"])}"' in panel, job["name"]
    assert panel.count('stroke="#111"') == len(r["critical_path"]) + 1  # and the legend's
    assert any(j["name"].startswith("damping: d ") for j in r["jobs"])  # the load cases' runs
    png = browser.screenshot(url, tmp_path / "timeline.png", size=(1280, 2600))
    import matplotlib.pyplot as plt

    pixels = (plt.imread(png)[..., :3] * 255).round().astype(int).reshape(-1, 3)
    case_green = np.array([0x2C, 0xA0, 0x2C])  # the load cases' bars (only there)
    assert (np.abs(pixels - case_green).sum(axis=1) <= 6).sum() > 100


def test_browser_shows_parameter_sets(finished):
    ps = finished["parameter_set"]
    dom = browser.dump_dom(f"{finished['url']}/#/parameter-sets")
    row = text_of(element(dom, "tr", f'data-id="{ps["id"]}"'))
    assert "web view box" in row and ps["id"] in row
    assert "E 10000 Pa" in row and "ν 0.45, ρ 1040 kg/m³" in row  # material
    assert "box (full), 30 × 30 × 30 mm, 64 nodes" in row  # geometry summary
    assert f"{js_num(ps['geometry']['h'] * 1e3)} mm" in row  # h
    assert f"{js_num(ps['k'])} N/m (one k: axis, face, body)" in row and "single" in row
    assert f"{js_num(ps['d'])} N s/m at dt 1 ms" in row
    assert " / ".join(pct(v) for v in ps["relative_discrepancy"]) in row
    assert "% of h: " + " / ".join(pct(v) for v in ps["discrepancy_h"]) in row
    assert ps["provenance"]["calibration_id"] in row


def test_the_parameter_set_page_downloads_its_exports(finished):
    """The export buttons wait out the worker's 202s and save the file the service sends."""
    ps = finished["parameter_set"]
    with httpx.Client(base_url=finished["url"], timeout=10) as http:
        expected = {}
        for fmt in ("json", "sofa"):
            answer = wait_for(
                f"{fmt} export",
                lambda fmt=fmt: http.get(f"/v1/parameter-sets/{ps['id']}/export?format={fmt}"),
                lambda r: r.status_code == 200,
                timeout=60,
            )
            expected[fmt] = len(answer.content)
    with browser.Browser() as page:
        page.open(f"{finished['url']}/#/parameter-sets/{ps['id']}")
        page.wait_for("document.querySelector('#exports button[data-format=json]')")
        for fmt, suffix in (("json", "json"), ("sofa", "scn")):
            page.js(f"document.querySelector('#exports button[data-format={fmt}]').click()")
            page.wait_for(f"document.getElementById('export-status').dataset.done === '{fmt}'")
            text = page.js("document.getElementById('export-status').textContent")
            assert text == f"{ps['id']}.{suffix}: {expected[fmt]} bytes"


# --- The cancel button with API keys set --------------------------------------------------------

KEY = "web-view-key-7d1c"


@pytest.fixture
def keyed_api(redis_server) -> Iterator[tuple[str, Any]]:
    """The real API under uvicorn with an API key, on its own db and with no worker (so what
    is submitted stays queued until canceled); the db is flushed afterwards."""
    redis_url = redis_server.url.rsplit("/", 1)[0] + "/3"
    port = free_port()
    env = {**os.environ, "REDIS_URL": redis_url, "FPM_API_KEYS": KEY}
    process = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "service.main:app", "--port", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}"
    http = httpx.Client(base_url=url, headers={"X-API-Key": KEY}, timeout=5)

    def up() -> bool:
        try:
            return http.get("/v1/health").status_code == 200
        except httpx.HTTPError:
            return process.poll() is not None  # exited: fail below

    try:
        wait_for("the keyed API", up, bool, timeout=60)
        assert process.poll() is None, "uvicorn exited"
        yield url, http
    finally:
        http.close()
        stop_process(process)
        from redis import Redis

        with Redis.from_url(redis_url) as r:
            r.flushdb()


def test_cancel_button_asks_for_the_api_key(chromium, keyed_api, small_spec):
    url, http = keyed_api
    small_spec["name"] = "to be canceled"
    calibration = http.post("/v1/calibrations", json=small_spec).json()
    assert calibration["status"] == "queued"
    with browser.Browser() as page:
        page.open(f"{url}/#/calibrations/{calibration['id']}")
        reason = "document.getElementById('key-reason').textContent"
        form_shown = "!document.getElementById('key-form').hidden"
        page.wait_for(form_shown)
        assert "API key" in page.js(reason)

        def give(key: str) -> None:
            page.js(
                f"document.getElementById('key-input').value = {key!r};"
                "document.getElementById('key-form').requestSubmit()"
            )

        give("wrong")
        page.wait_for(f"{form_shown} && {reason}.includes('refused')")
        give(KEY)
        page.wait_for("document.querySelector('#summary [data-status=queued]')")
        assert page.js("sessionStorage.getItem('fpm-api-key')") == KEY
        page.js("document.querySelector('[data-action=cancel]').click()")
        page.wait_for("document.querySelector('[data-action=confirm-cancel]')")
        page.js("document.querySelector('[data-action=confirm-cancel]').click()")
        page.wait_for("document.querySelector('#summary [data-status=canceled]')")
        assert page.js("document.querySelector('[data-action=cancel]')") is None
    assert http.get(f"/v1/calibrations/{calibration['id']}").json()["status"] == "canceled"


def test_browser_shows_the_verdict_first_and_the_compliance_per_case(finished, tmp_path):
    """The summary card carries the verdict (grade in capitals, summary, floor, each cause
    with its action) above the figures; the fit table a compliance column; the parameter
    set's page the same verdict."""
    c, names = finished["calibration"], finished["names"]
    r, v = c["result"], c["result"]["verdict"]
    url = f"{finished['url']}/#/calibrations/{c['id']}"
    dom = browser.dump_dom(url)
    card = element(dom, "div", f'class="verdict verdict-{v["grade"]}"')
    assert dom.index(card) < dom.index('id="fit"')  # above the figures
    text = text_of(card)
    assert text.startswith(f"{v['grade'].upper()} {v['summary'][len(v['grade']) + 2 :]}")
    assert v["floor"]["source"] in text
    for cause in v["causes"]:
        assert f"{cause['cause']} : {cause['detail']}. Action: {cause['action']}" in text
    fit = text_of(element(dom, "div", 'class="panel" id="fit"'))
    assert "Compliance" in fit
    for j, name in enumerate(names):
        figures = f"{pct(r['discrepancy_h'][j])} {r['settle_steps'][j]}"
        assert f"{figures} {r['compliance_ratio'][j]:.3f}" in fit, name
    page = browser.dump_dom(f"{finished['url']}/#/parameter-sets/{c['parameter_set_id']}")
    assert text_of(element(page, "div", f'class="verdict verdict-{v["grade"]}"')) == text
    png = browser.screenshot(url, tmp_path / "verdict.png", size=(1280, 900))
    assert browser.distinct_colours(png) > 50
    copy_to = os.environ.get("FPM_WEB_VERDICT_SCREENSHOT")
    if copy_to:
        shutil.copyfile(png, copy_to)
