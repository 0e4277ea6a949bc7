"""The web view's live model (service/static/web/fpm-step.js, live-worker.js) in headless Chromium,
for tests/web/test_live_step.py and bench/bench_live.py.

:func:`serve` is a small HTTP server of our own on a free port (a thread of this process): ``/``
a blank page, ``/web/...`` the web view's static files, ``/data/...`` the files of a directory
(the JSON exports), ``/later/...`` the same files after a first 202 (an export being made:
``Retry-After: 1``). Module scripts and module workers need an http origin (Chromium refuses
them from file://), and the page carries the service's own policy for them (scripts, workers
and fetches from the same origin only), so what runs here runs in the web view.
:func:`open_live_page` opens it in a :class:`browser.Browser` and imports fpm-step.js as
``window.fpm``. :func:`cube_export` and :func:`organ_export` build the exports the tests and the
bench step: the paper's cube and the voxel organ, families+volume at the continuum start.
"""

from __future__ import annotations

import functools
import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "service" / "static" / "web"
POLICY = (
    "default-src 'none'; script-src 'self'; worker-src 'self'; connect-src 'self'; base-uri 'none'"
)
"""The page's Content-Security-Policy: the web view's, as far as scripts and workers go."""
PAGE = b"<!doctype html><html><head><meta charset='utf-8'><title>live</title></head></html>"


class _Handler(SimpleHTTPRequestHandler):
    data: Path = ROOT
    asked: set[str] = set()

    def translate_path(self, path: str) -> str:
        path = path.split("?", 1)[0].split("#", 1)[0]
        for prefix, base in (("/web/", STATIC), ("/data/", self.data)):
            if path.startswith(prefix):
                name = path.removeprefix(prefix)
                target = (base / name).resolve()
                if base.resolve() in target.parents:
                    return str(target)
        return str(self.data / "__nothing__")

    def do_GET(self) -> None:  # noqa: N802 (the base class's name)
        if self.path.startswith("/later/"):
            if self.path not in self.asked:
                self.asked.add(self.path)
                self.send_response(202)
                self.send_header("Retry-After", "1")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.path = "/data/" + self.path.removeprefix("/later/")
        if self.path.split("?", 1)[0] in ("/", "/index.html"):
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(PAGE)))
            self.end_headers()
            self.wfile.write(PAGE)
            return
        super().do_GET()

    def end_headers(self) -> None:
        self.send_header("Content-Security-Policy", POLICY)
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
        pass


@contextmanager
def serve(data: Path) -> Iterator[str]:
    """An HTTP server for the page, the web view's files and ``data``; yields its base URL."""
    handler = type("Handler", (_Handler,), {"data": Path(data), "asked": set()})
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


def open_live_page(browser: Any, base: str) -> None:
    """Open the blank page at ``base`` and import fpm-step.js as ``window.fpm``."""
    browser.open(f"{base}/")
    browser.wait_for("document.readyState === 'complete'")
    browser.js("import('/web/fpm-step.js').then(m => { window.fpm = m; return true; })")


def exported(spec: dict[str, Any]) -> dict[str, Any]:
    """The parsed JSON export of ``spec`` at the continuum start, d half the critical scale
    (tests/core/test_runtime.py's ``exported``)."""
    import numpy as np

    from fpm import load_problem
    from fpm.io.export import export
    from fpm.model.stiffness import continuum_start, stiffness_dict, volume_stiffness

    problem = load_problem(spec)
    theta = continuum_start(problem)
    e, h = problem.spec.material.youngs_modulus, problem.h
    record = {
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": 0.5 * float(np.sqrt(e * h * problem.solid.masses.mean())),
        "depth": 30,
    }
    doc: dict[str, Any] = json.loads(export(problem, record, "json"))
    return doc


def cube_export() -> dict[str, Any]:
    """The paper's cube (10^3 nodes, full connectivity), families+volume, dt auto."""
    spec = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    spec["fpm"] = {"stiffness": "families+volume", "dt": "auto"}
    return exported(spec)


def organ_export(h: float) -> dict[str, Any]:
    """The voxel organ (bench/organ.py) at spacing ``h`` m, families+volume, dt auto."""
    import sys

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench.organ import ellipsoid_spec

    return exported(ellipsoid_spec(h, fpm={"stiffness": "families+volume", "dt": "auto"}))


def conforming_spec(h: float) -> dict[str, Any]:
    """The 480-tetrahedron organ (bench/tet_organ.py) as ``spec_from_mesh`` makes it with the
    defaults: the surface-conforming lattice of spacing ``h`` m (hexahedra of every shape)."""
    import sys

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench.tet_organ import surface_spec

    spec: dict[str, Any] = surface_spec("organ", h)
    assert spec["geometry"]["type"] == "mesh"  # the conforming lattice, not voxels
    del spec["reference"], spec["validation_cases"]
    return spec
