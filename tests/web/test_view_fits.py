"""The web view fits the mesh: the 3D view's up axis comes from the mesh (against gravity, else
away from the fixed nodes), a long load-case name wraps inside its card, the 3D header's figures
are the calibration result's, and an organ's profile runs along the load's own line when no
lattice line passes through its loaded node. In headless Chromium (tests/browser.py), looked at
through screenshots: the loaded nodes' markers (the only pink on the page) are drawn in the upper
half of the canvas, above the held side, for a y-up and a z-up solid.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import browser
import httpx
import numpy as np
import pytest
from conftest import SMALL_SPEC
from test_view import TERMINAL, canvas_pixels, wait_for

from fpm.io.plot import profile_line

pytestmark = pytest.mark.redis

ROOT = Path(__file__).resolve().parents[2]
PAPER_SPEC = json.loads((ROOT / "examples" / "paper-material-a.json").read_text())
LONG_NAME = (
    "a pull on the far end of the tall box, straight along y away from its held foot, "
    "the first of two load cases with long names"
)


@pytest.fixture(scope="module")
def chromium() -> str:
    path, why = browser.chromium()
    if path is None:
        pytest.skip(f"no headless browser for the web view's tests: {why}")
    return path


def y_up_spec() -> dict[str, Any]:
    """A tall box standing on its y- face, pulled at its top along +y: no gravity, so the view's
    up axis is the fixed nodes' side's opposite, +y."""
    spec = copy.deepcopy(SMALL_SPEC)
    spec["name"] = "3D view: a y-up box"
    spec["geometry"] = {"type": "box", "size": [0.03, 0.06, 0.03], "nodes": [4, 7, 4]}
    spec["fixed"] = [{"face": "y-"}]
    spec["load_cases"] = [
        {"name": LONG_NAME, "forces": [{"at": [0.01, 0.06, 0.01], "vector": [0, 0.05, 0]}]},
        {"name": "0.1 N", "forces": [{"at": [0.01, 0.06, 0.01], "vector": [0, 0.1, 0]}]},
    ]
    return spec


def calibrated(url: str, spec: dict[str, Any]) -> dict[str, Any]:
    """A succeeded calibration of ``spec`` on the live stack, its 3D view's data made."""
    with httpx.Client(base_url=url, timeout=30) as http:
        submitted = http.post("/v1/calibrations", json=spec).json()
        path = f"/v1/calibrations/{submitted['id']}"
        calibration = wait_for(
            "calibration", lambda: http.get(path).json(), lambda c: c["status"] in TERMINAL
        )
        assert calibration["status"] == "succeeded", calibration
        ps = calibration["parameter_set_id"]
        view = wait_for(
            "3D view data",
            lambda: http.get(f"/v1/parameter-sets/{ps}/view"),
            lambda r: r.status_code != 202,
            timeout=120,
        )
        assert view.status_code == 200, view.text
    return calibration


def pink_rows(pixels: np.ndarray) -> np.ndarray:
    """Rows (0 = top) of the canvas's pink pixels: the loaded nodes' markers and force lines
    (#ff2a6d; viridis has no pink)."""
    r, g, b = (pixels[..., c].astype(int) for c in range(3))
    pink = (r > 180) & (g < 120) & (b > 60) & (b < 170) & (r - b > 60)
    return np.nonzero(pink)[0]


def open_3d(page: browser.Browser, url: str, ps: str) -> None:
    page.open(f"{url}/#/parameter-sets/{ps}/3d")
    page.viewport(1280, 1150)
    page.wait_for(
        "document.getElementById('view3d') && document.getElementById('view3d').dataset.ready"
    )
    page.wait_for("Number(document.getElementById('view3d-canvas').dataset.frames) > 0")
    page.js("new Promise(done => requestAnimationFrame(() => setTimeout(done, 100)))")


@pytest.mark.parametrize(
    ("which", "up"), [("paper cube (z up)", "+z"), ("tall box (y up)", "+y")], ids=["z", "y"]
)
def test_the_3d_view_stands_the_solid_on_its_held_side(live_api, chromium, tmp_path, which, up):
    spec = copy.deepcopy(PAPER_SPEC) if up == "+z" else y_up_spec()
    spec["name"] = f"3D view: {which}"
    calibration = calibrated(live_api, spec)
    ps = calibration["parameter_set_id"]
    with browser.Browser(timeout=60) as page:
        open_3d(page, live_api, ps)
        assert page.js("document.getElementById('view3d').dataset.up") == up
        assert f"Up: {up} (away from the fixed nodes)" in page.js(
            "document.getElementById('view3d-up').textContent"
        )
        facts = page.js("document.getElementById('view3d-facts').textContent")
        steps = calibration["result"]["settle_steps"][0]
        assert f"settled in {steps:,} steps (the calibration's final run)" in facts
        png = page.screenshot(tmp_path / f"up{up[1]}.png")
        pixels = canvas_pixels(page, png)
        rows = pink_rows(pixels)
        assert len(rows) > 30, len(rows)  # the markers are drawn
        assert np.median(rows) < 0.45 * len(pixels), (np.median(rows), len(pixels))
        assert page.console_errors() == []
        keep = os.environ.get("FPM_WEB_SCREENSHOT_DIR")
        if keep:
            shutil.copyfile(png, Path(keep) / f"view3d-up{up[1]}.png")


def test_a_long_load_case_name_wraps_inside_its_card(live_api, chromium, tmp_path):
    calibration = calibrated(live_api, y_up_spec())
    with browser.Browser(timeout=60) as page:
        page.open(f"{live_api}/#/calibrations/{calibration['id']}")
        page.viewport(1280, 1150)
        page.wait_for("document.querySelector('#fit table')")
        fit = page.js(
            "(() => { const p = document.getElementById('fit').getBoundingClientRect();"
            " const t = document.querySelector('#fit table').getBoundingClientRect();"
            " const cell = document.querySelector('#fit tbody td').getBoundingClientRect();"
            " return [p.left, p.right, t.left, t.right, cell.height,"
            " document.getElementById('fit').scrollWidth,"
            " document.getElementById('fit').clientWidth]; })()"
        )
        page.screenshot(tmp_path / "long-name.png")
        keep = os.environ.get("FPM_WEB_SCREENSHOT_DIR")
        if keep:
            shutil.copyfile(tmp_path / "long-name.png", Path(keep) / "long-name.png")
        panel_left, panel_right, table_left, table_right, cell_height, scroll, client = fit
        assert panel_left <= table_left and table_right <= panel_right + 0.5, fit
        assert scroll <= client, fit  # nothing sticks out of the card
        assert cell_height > 30, fit  # the name runs over more than one line
        assert page.js("document.querySelector('#fit tbody td').textContent") == LONG_NAME
        heights = page.js(
            "[...document.querySelectorAll('#fit tbody tr:first-child td.num')]"
            ".map(td => [td.textContent, td.getClientRects().length,"
            " Math.round(td.firstChild ? (() => { const r = document.createRange();"
            " r.selectNodeContents(td); return r.getClientRects().length; })() : 0)])"
        )
        assert all(lines == 1 for _, _, lines in heights), heights  # figures stay whole
        open_3d(page, live_api, calibration["parameter_set_id"])
        toolbar = page.js(
            "(() => { const p = document.getElementById('view3d').getBoundingClientRect();"
            " const s = document.getElementById('view3d-case').getBoundingClientRect();"
            " return [p.right, s.right]; })()"
        )
        assert toolbar[1] <= toolbar[0], toolbar
        assert page.console_errors() == []


def test_an_off_grid_loaded_node_is_profiled_along_the_loads_own_line():
    """A conformed lattice moves its surface nodes off the grid: no axis-parallel line through
    the loaded node holds another node, so the profile runs along the force's line through it
    (here a column of nodes 0.2 h off it, and a node 2 h off it that is left out)."""
    h = 0.01
    column = [[0.002, 0.001, h * i] for i in range(6)]
    loaded = [0.0, 0.0, 5 * h + 0.003]
    nodes = np.array([*column, [0.02, 0.0, 0.01], loaded])
    case = SimpleNamespace(nodes=np.array([7]), forces=np.array([[0.0, 0.0, -1.0]]))
    problem = SimpleNamespace(nodes=nodes, h=h, load_cases=[case])
    line, along, direction = profile_line(problem, 0)  # type: ignore[arg-type]
    assert (along, direction) == (2, 2)
    assert list(line) == [0, 1, 2, 3, 4, 5, 7]  # along z, the far node left out
