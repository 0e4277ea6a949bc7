"""The 3D view's push mode (service/static/web/live.js) in headless Chromium, on the live stack:
the button fetches the parameter set's JSON export, starts the worker, a surface node dragged with
the mouse moves the drawn lattice, and let go it swings back to rest.

The paper's cube is calibrated and its view made as tests/web/test_view.py does (its fixtures);
skipped, with the reason, only where no Chromium can be had.
"""

from __future__ import annotations

from typing import Any

import browser
import numpy as np
import pytest
from test_view import canvas_pixels, chromium, paper_cube  # noqa: F401 (fixtures)

pytestmark = pytest.mark.redis

CANVAS = "document.getElementById('view3d-canvas')"


def mouse(page: browser.Browser, kind: str, x: float, y: float) -> None:
    """A left-button mouse event at (x, y) CSS pixels (Chromium makes the pointer events)."""
    page.call(
        "Input.dispatchMouseEvent",
        {
            "type": kind,
            "x": x,
            "y": y,
            "button": "left",
            "buttons": 0 if kind == "mouseReleased" else 1,
            "clickCount": 1,
        },
    )


def live(page: browser.Browser) -> dict[str, Any]:
    state: dict[str, Any] = page.js(f"({{...{CANVAS}.dataset}})")
    return state


def test_push_mode_drags_a_node_and_the_model_swings_back(paper_cube, tmp_path):  # noqa: F811
    ps = paper_cube["parameter_set_id"]
    with browser.Browser(timeout=60) as page:
        page.open(f"{paper_cube['url']}/#/parameter-sets/{ps}/3d")
        page.viewport(1280, 1150)
        page.wait_for(
            "document.getElementById('view3d') && document.getElementById('view3d').dataset.ready"
        )
        before = canvas_pixels(page, page.screenshot(tmp_path / "before.png"))

        page.js("document.getElementById('view3d-push').click()")
        page.wait_for(f"{CANVAS}.dataset.live === 'ready'", timeout=180)  # a worker made the export
        status = page.js("document.getElementById('view3d-live').textContent")
        assert status.startswith("Live: 1,000 nodes, stepped at the engine's dt = "), status
        pressed = page.js("document.getElementById('view3d-push').getAttribute('aria-pressed')")
        assert pressed == "true"

        # Press on the cube's face nearest the camera (the canvas's centre), drag up by 30 px.
        box = page.js(
            f"(() => {{ const r = {CANVAS}.querySelector('canvas').getBoundingClientRect();"
            " return [r.left + r.width / 2, r.top + r.height / 2]; })()"
        )
        x, y = box
        mouse(page, "mouseMoved", x, y)
        mouse(page, "mousePressed", x, y)
        page.wait_for(f"{CANVAS}.dataset.live === 'dragging'")
        node = int(live(page)["liveNode"])
        for k in range(1, 7):
            mouse(page, "mouseMoved", x, y - 5 * k)
        page.wait_for(f"Number({CANVAS}.dataset.liveMoved) > 1e-3")  # 1 mm, h = 11 mm
        status = page.js("document.getElementById('view3d-live-state').textContent")
        assert status.startswith(f"Pulling node {node} with "), status
        # The pull is capped (FpmModel.stepForceLimit): the model settles under it and idles.
        page.wait_for(f"Number({CANVAS}.dataset.liveSteps) > 100")
        pulled = canvas_pixels(page, page.screenshot(tmp_path / "pulled.png"))
        changed = (np.abs(pulled.astype(int) - before.astype(int)).sum(axis=2) > 30).mean()
        assert changed > 0.002, changed
        moved = float(live(page)["liveMoved"])

        mouse(page, "mouseReleased", x, y - 30)
        page.wait_for(f"{CANVAS}.dataset.live === 'ready'")
        page.wait_for(f"Number({CANVAS}.dataset.liveMoved) < {0.01 * moved!r}", timeout=120)
        status = page.js("document.getElementById('view3d-live-state').textContent")
        assert status.startswith(("At rest", "Swinging back")), status

        page.js("document.getElementById('view3d-push').click()")  # stop
        page.wait_for(f"!('live' in {CANVAS}.dataset) && !document.getElementById('view3d-live')")
        assert page.js("document.getElementById('view3d-push').textContent") == "Push (live)"
        assert page.console_errors() == []
