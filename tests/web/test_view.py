"""The 3D view of a parameter set: its data route ``GET /v1/parameter-sets/{id}/view``
(made by a worker, cached like an export: 202 then 200, gzip; 404, 410, 503, recomputed after
expiry), the body's layout and fields (the outer surface is exactly the unshared hexahedron
faces; the FEM and FPM fields are the stored reference's and fpm.simulate's / the static
equilibrium's), the page's assets and Content-Security-Policy, and the page in headless
Chromium (WebGL through SwiftShader, tests/browser.py) on the paper's cube: the screenshot's
pixels are drawn, coloured, and change with the load case; no console error.

``FPM_WEB_SCREENSHOT_3D=docs/web-view-3d.png`` also saves the 3D view's screenshot there (the
README's picture).
"""

from __future__ import annotations

import copy
import json
import os
import re
import shutil
import struct
import time
from collections import Counter
from pathlib import Path
from typing import Any

import browser
import httpx
import numpy as np
import pytest
from conftest import SMALL_SPEC
from fastapi.testclient import TestClient
from test_service import assert_problem

import fpm
from fpm.dynamics.equilibrium import static_equilibrium
from fpm.model.stiffness import fitted_theta
from service.web import CONTENT_SECURITY_POLICY
from store import graph, keys, records, scratch
from store.hashing import view_hash
from worker.view import FACES, surface_quads

pytestmark = pytest.mark.redis

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "service" / "static" / "web"
PAPER_SPEC = json.loads((ROOT / "examples" / "paper-material-a.json").read_text())
TERMINAL = ("succeeded", "failed", "canceled")


def decode(body: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The body's header and arrays, read here from the documented layout (b"FPMV", uint32
    header length, JSON header, little-endian arrays at their offsets)."""
    assert body[:4] == b"FPMV"
    (length,) = struct.unpack("<I", body[4:8])
    assert length % 4 == 0
    header = json.loads(body[8 : 8 + length])
    arrays = {}
    for name, entry in header["arrays"].items():
        assert entry["offset"] % 4 == 0 and entry["offset"] >= 8 + length
        dtype = {"float32": "<f4", "uint32": "<u4"}[entry["dtype"]]
        count = int(np.prod(entry["shape"]))
        arrays[name] = np.frombuffer(body, dtype, count, entry["offset"]).reshape(entry["shape"])
    return header, arrays


def unshared_faces(hexahedra: np.ndarray) -> set[tuple[int, ...]]:
    """The faces (as sorted node tuples) that exactly one hexahedron has, counted plainly."""
    faces = Counter(
        tuple(sorted(int(n) for n in hexahedron[face]))
        for hexahedron in hexahedra
        for face in FACES
    )
    return {face for face, count in faces.items() if count == 1}


def quads_of(triangles: np.ndarray) -> np.ndarray:
    """The quads (a, b, c, d) back from the triangle pairs (a, b, c), (a, c, d)."""
    pairs = np.asarray(triangles).reshape(-1, 2, 3)
    assert np.array_equal(pairs[:, 0, 0], pairs[:, 1, 0])  # a
    assert np.array_equal(pairs[:, 0, 2], pairs[:, 1, 1])  # c
    return np.column_stack([pairs[:, 0, 0], pairs[:, 0, 1], pairs[:, 0, 2], pairs[:, 1, 2]])


# --- The surface ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "geometry",
    [
        {"type": "box", "size": [0.03, 0.02, 0.04], "nodes": [4, 3, 5]},
        # a 3x3x3 block of voxels without its centre (a closed cavity) and one corner
        {
            "type": "voxels",
            "spacing": [0.01, 0.01, 0.01],
            "occupancy": [
                [[i != 2 or j != 2 or k != 2 for k in range(3)] for j in range(3)]
                if i != 1
                else [[not (j == 1 and k == 1) for k in range(3)] for j in range(3)]
                for i in range(3)
            ],
        },
    ],
)
def test_the_surface_is_the_unshared_faces_pointing_out(geometry):
    spec = {**copy.deepcopy(SMALL_SPEC), "geometry": geometry}
    spec["load_cases"][0]["forces"][0] = {"nearest": [0.01, 0.01, 0.03], "vector": [0, 0, 0.05]}
    spec["load_cases"] = spec["load_cases"][:1]
    problem = fpm.load_problem(spec)
    hexahedra = problem.solid.elements()
    quads = surface_quads(hexahedra)
    assert {tuple(sorted(q)) for q in quads.tolist()} == unshared_faces(hexahedra)
    assert len(quads) == len(unshared_faces(hexahedra))
    if geometry["type"] == "box":
        cx, cy, cz = (n - 1 for n in geometry["nodes"])
        assert len(quads) == 2 * (cx * cy + cy * cz + cx * cz)
    else:  # 54 outside (the cut corner takes 3 and shows 3), and the cavity's 6
        assert len(quads) == 54 + 6
    # Counter-clockwise seen from outside the hexahedron that has the face.
    nodes = problem.nodes
    owner = {}
    for h, hexahedron in enumerate(hexahedra):
        for face in FACES:
            owner.setdefault(tuple(sorted(hexahedron[face].tolist())), h)
    for quad in quads:
        a, b, c = nodes[quad[:3]]
        normal = np.cross(b - a, c - a)
        outward = nodes[quad].mean(axis=0) - nodes[hexahedra[owner[tuple(sorted(quad))]]].mean(0)
        assert normal @ outward > 0


# --- The data route, in process -------------------------------------------------------------------


def calibrated(api: TestClient, run_workers: Any, spec: dict[str, Any]) -> dict[str, Any]:
    submitted = api.post("/v1/calibrations", json=spec).json()
    run_workers()
    done = api.get(f"/v1/calibrations/{submitted['id']}").json()
    assert done["status"] == "succeeded", done
    return done


@pytest.fixture
def with_validation(small_spec: dict[str, Any]) -> dict[str, Any]:
    small_spec["validation_cases"] = [
        {"name": "sideways", "forces": [{"at": [0.01, 0.01, 0.03], "vector": [0.05, 0, 0]}]}
    ]
    return small_spec


def test_the_view_route_is_pending_then_the_fields(api, redis, run_workers, with_validation):
    done = calibrated(api, run_workers, with_validation)
    ps_id = done["parameter_set_id"]
    path = f"/v1/parameter-sets/{ps_id}/view"
    first = api.get(path)
    assert first.status_code == 202 and first.json() == {"status": "pending", "retry_after": 1}
    assert first.headers["Retry-After"] == "1" and first.headers["Location"] == path
    assert api.get(path).status_code == 202
    assert graph.priority_queue(redis).count == 1  # one job however often it is asked
    assert graph.priority_queue(redis).jobs[0].id == keys.view_job_id(view_hash(ps_id))
    run_workers()
    answer = api.get(path)
    assert answer.status_code == 200
    assert answer.headers["content-type"] == "application/octet-stream"
    assert answer.headers["content-encoding"] == "gzip"  # sent as cached (httpx unpacked it)
    cached = scratch.get_export(redis, view_hash(ps_id))
    assert cached is not None and 0 < redis.ttl(keys.export(view_hash(ps_id))) <= 24 * 3600
    plain = api.get(path, headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.content == answer.content

    header, arrays = decode(answer.content)
    ps = api.get(f"/v1/parameter-sets/{ps_id}").json()
    record = records.get_calibration(redis, done["id"])
    assert record is not None
    problem = fpm.load_problem(record.spec)
    assert header["format"] == "fpm-view" and header["parameter_set_id"] == ps_id
    assert header["h"] == pytest.approx(ps["geometry"]["h"]) and header["nodes"] == 64
    # 4x4x4 nodes: 56 on the surface, 6 faces of 3x3 quads; no marked node inside.
    assert header["surface_vertices"] == header["vertices"] == 56
    assert header["triangles"] == 2 * 54
    assert np.allclose(header["bounds"], [[0, 0, 0], [0.03, 0.03, 0.03]])
    v = header["vertices"]
    shapes = {name: tuple(a.shape) for name, a in arrays.items()}
    assert shapes["positions"] == (v, 3) and arrays["positions"].dtype == "<f4"
    assert shapes["triangles"] == (108, 3) and arrays["triangles"].dtype == "<u4"
    assert shapes["node_index"] == (v,) and shapes["fixed"] == (16,)
    index = arrays["node_index"].astype(int)
    assert len(set(index)) == v
    assert np.allclose(arrays["positions"], problem.nodes[index], atol=1e-7)
    # The triangles, two per quad, are exactly the unshared hexahedron faces.
    quads = index[quads_of(arrays["triangles"])]
    assert {tuple(sorted(q)) for q in quads.tolist()} == unshared_faces(problem.solid.elements())
    assert sorted(index[arrays["fixed"]]) == np.flatnonzero(problem.fixed).tolist()

    # Per case: fitted, then validation; FEM from the stored reference (= solve_fem), FPM from
    # fpm.simulate at the set's parameters (fitted) or its static equilibrium (validation).
    cases = header["cases"]
    assert [(c["name"], c["kind"]) for c in cases] == [
        ("0.05 N", "fitted"),
        ("0.1 N", "fitted"),
        ("sideways", "validation"),
    ]
    fem = np.array(
        api.get(f"/v1/fem-references/{done['fem_reference_id']}").json()["displacements"]
    )
    assert fem.shape == (3, 64, 3)
    assert np.allclose(fem, fpm.solve_fem(problem).displacements, rtol=1e-9, atol=1e-15)
    theta = fitted_theta(problem, ps)
    checked = problem.validation_problem()
    for i, case in enumerate(cases):
        fitted = case["kind"] == "fitted"
        j = i if fitted else i - 2
        if fitted:
            run = fpm.simulate(
                problem, k=theta, d=ps["damping"], depth=ps["depth"], load_case=j, dt=ps["dt"]
            )
            p, loaded = run.displacements, problem.load_cases[j]
            assert case["steps"] == run.steps and case["settled"] is True
            for name in ("relative_discrepancy", "loaded_discrepancy", "discrepancy_h"):
                assert case[name] == ps[name][j], name
        else:
            p = static_equilibrium(checked, k=theta, depth=64, load_case=j).displacements
            loaded = checked.load_cases[j]
            assert case["relative_discrepancy"] == ps["validation_relative_discrepancy"][j]
            assert case["discrepancy_h"] == ps["validation_discrepancy_h"][j]
            assert case["loaded_discrepancy"] is None and case["settled"] is True
        q = fem[i]
        names = case["arrays"]
        assert shapes[names["fem"]] == shapes[names["fpm"]] == (v, 3)
        assert np.allclose(arrays[names["fem"]], q[index], rtol=1e-6, atol=1e-12)
        assert np.allclose(arrays[names["fpm"]], p[index], rtol=1e-5, atol=1e-10)
        assert np.abs(p).max() > 0 and not np.allclose(arrays[names["fpm"]], 0)
        assert index[arrays[names["loaded"]]].tolist() == loaded.nodes.tolist()
        assert np.allclose(arrays[names["forces"]], loaded.forces)
        assert case["fem_max"] == pytest.approx(np.linalg.norm(q, axis=1).max())
        assert case["discrepancy_max"] == pytest.approx(np.linalg.norm(p - q, axis=1).max())
    assert graph.priority_queue(redis).count == 0 and api.get(path).content == answer.content


def test_a_view_whose_cache_expired_is_made_again(api, redis, run_workers, small_spec):
    done = calibrated(api, run_workers, small_spec)
    path = f"/v1/parameter-sets/{done['parameter_set_id']}/view"
    assert api.get(path).status_code == 202
    run_workers()
    made = api.get(path)
    assert made.status_code == 200
    key = keys.export(view_hash(done["parameter_set_id"]))
    redis.pexpire(key, 1)  # the day is over
    time.sleep(0.01)
    assert not redis.exists(key)
    again = api.get(path)
    assert again.status_code == 202 and again.json()["status"] == "pending"
    run_workers()
    remade = api.get(path)
    assert remade.status_code == 200 and remade.content == made.content


def test_unknown_gone_and_failed_views_are_problems_not_500s(api, redis, run_workers, small_spec):
    assert (
        "no parameter set"
        in assert_problem(api.get("/v1/parameter-sets/ps-0123456789abcdef/view"), 404)["detail"]
    )
    assert_problem(api.get("/v1/parameter-sets/nope/view"), 404)
    assert_problem(api.get("/v1/parameter-sets/ps-0123456789abcdef/view/x"), 404)

    done = calibrated(api, run_workers, small_spec)
    path = f"/v1/parameter-sets/{done['parameter_set_id']}/view"
    # A FEM reference that is gone: the job stores why, the route answers 503 with
    # Retry-After (the cool-down), not a 500, and does not enqueue again meanwhile.
    redis.delete(keys.fem_reference(done["fem_reference_id"]))
    assert api.get(path).status_code == 202
    run_workers()
    failed = api.get(path)
    body = assert_problem(failed, 503)
    assert "no longer stored" in body["detail"] and 0 < int(failed.headers["Retry-After"]) <= 600
    assert graph.priority_queue(redis).count == 0
    # Parameters that do not fit the spec's lattice: 422 (the job's finding, kept for the
    # cool-down like any failure).
    other = calibrated(api, run_workers, {**small_spec, "name": "another box"})
    ps_key = keys.parameter_set(other["parameter_set_id"])
    stored = json.loads(redis.get(ps_key))
    stored["geometry"]["nodes"] = 65
    redis.set(ps_key, json.dumps(stored))
    other_path = f"/v1/parameter-sets/{other['parameter_set_id']}/view"
    assert api.get(other_path).status_code == 202
    run_workers()
    body = assert_problem(api.get(other_path), 422)
    assert [e["field"] for e in body["errors"]] == ["parameter_set_id"]
    assert "fitted on 65 nodes; the spec builds 64" in body["detail"]
    # Its calibration record gone: 410.
    redis.delete(keys.calibration(done["id"]))
    redis.delete(keys.export_failure(view_hash(done["parameter_set_id"])))
    assert "calibrate its spec again" in assert_problem(api.get(path), 410)["detail"]


def test_the_route_is_documented(api):
    operation = api.get("/openapi.json").json()["paths"][
        "/v1/parameter-sets/{parameter_set_id}/view"
    ]
    operation = operation["get"]
    assert operation["operationId"] == "get_parameter_set_view"
    responses = operation["responses"]
    assert {"200", "202", "401", "404", "410", "422", "500", "503"} == set(responses)
    assert responses["200"]["content"] == {
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}
    }
    assert {"Retry-After", "Location"} <= set(responses["202"]["headers"])


# --- The page's assets ---------------------------------------------------------------------


def test_the_page_allows_only_its_own_origin_and_serves_three_from_it(api):
    page = api.get("/")
    policy = page.headers["content-security-policy"]
    assert policy == CONTENT_SECURITY_POLICY
    directives = dict(d.split(" ", 1) for d in policy.split("; "))
    assert directives["default-src"] == "'none'"
    for name in ("script-src", "worker-src", "style-src", "connect-src", "img-src"):
        assert directives[name] == "'self'", name
    assert "unsafe" not in policy and "http" not in policy and "*" not in policy
    for asset in (
        "view3d.js",
        "vendor/three/three.module.min.js",
        "vendor/three/OrbitControls.js",
        "favicon.svg",
    ):
        answer = api.get(f"/web/{asset}")
        assert answer.status_code == 200, asset
        if asset.endswith(".js"):
            assert "javascript" in answer.headers["content-type"]
    # The modules import only from this origin, by relative path; three.js imports nothing.
    for name, expected in (
        ("view3d.js", ["./vendor/three/three.module.min.js", "./vendor/three/OrbitControls.js"]),
        ("vendor/three/OrbitControls.js", ["./three.module.min.js"]),
        ("vendor/three/three.module.min.js", []),
    ):
        text = (STATIC / name).read_text()
        found = re.findall(r"""(?m)^import\b[^;]*?\bfrom\s*["']([^"']+)["']""", text)
        assert found == expected, name
        if name.startswith("vendor"):
            assert not re.search(r"""\bimport\s*\(""", text), name  # no dynamic import
    vendor = STATIC / "vendor" / "three"
    assert "MIT License" in (vendor / "LICENSE").read_text()
    note = (vendor / "README.md").read_text()
    assert "three@0.170.0" in note and (vendor / "VERSION").read_text().strip() == "0.170.0"
    assert 'const t="170"' in (vendor / "three.module.min.js").read_text()[:400]
    view3d = (STATIC / "view3d.js").read_text()
    assert not re.search(r"https?://", view3d) and "innerHTML" not in view3d
    assert "export class View3D" in view3d and "setNodePositions(positions)" in view3d


# --- In a real browser, on the paper's cube -----------------------------------------------------


@pytest.fixture(scope="module")
def chromium() -> str:
    path, why = browser.chromium()
    if path is None:
        pytest.skip(f"no headless browser for the web view's tests: {why}")
    return path


def wait_for(what: str, get: Any, done: Any, timeout: float = 180) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = get()
        if done(value):
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: still {value}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def paper_cube(live_api: str, chromium: str) -> dict[str, Any]:
    """The paper's cube (examples/paper-material-a.json: material A, 10x10x10 nodes, three
    forces) calibrated on the live stack, as the web view's tests get theirs (a few seconds),
    and its 3D view's data made."""
    spec = copy.deepcopy(PAPER_SPEC)
    spec["name"] = "3D view: the paper's cube"
    with httpx.Client(base_url=live_api, timeout=30) as http:
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
    return {"url": live_api, "calibration": calibration, "parameter_set_id": ps}


def canvas_pixels(page: browser.Browser, png: Path) -> np.ndarray:
    """The 3D canvas's pixels (RGB, 0-255) cut from a screenshot of the page."""
    import matplotlib.pyplot as plt

    box = page.js(
        "(() => { const r = document.querySelector('#view3d-canvas canvas')"
        ".getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; })()"
    )
    left, top, right, bottom = (round(v) for v in box)
    pixels = (plt.imread(png)[..., :3] * 255).round().astype(np.uint8)
    assert right - left > 400 and bottom - top > 300, box
    return pixels[top:bottom, left:right]


def hues(pixels: np.ndarray) -> Counter[int]:
    """Coloured pixels (saturation and value over 0.25) per 30-degree hue bin."""
    from matplotlib.colors import rgb_to_hsv

    hsv = rgb_to_hsv(pixels.reshape(-1, 3) / 255.0)
    coloured = hsv[(hsv[:, 1] > 0.25) & (hsv[:, 2] > 0.25)]
    return Counter((coloured[:, 0] * 12).astype(int) % 12)


def frames(page: browser.Browser) -> int:
    """Frames the 3D view has drawn so far."""
    return int(page.js("document.getElementById('view3d-canvas').dataset.frames || 0"))


def drawn_after(page: browser.Browser, before: int) -> None:
    """Wait until the view has drawn a frame after ``before`` frames, and it is on screen."""
    page.wait_for(f"Number(document.getElementById('view3d-canvas').dataset.frames) > {before}")
    page.js("new Promise(done => requestAnimationFrame(() => setTimeout(done, 50)))")


def show_case(page: browser.Browser, case: int, mode: str = "fpm") -> None:
    before = frames(page)
    page.js(
        "(() => { const s = document.getElementById('view3d-case');"
        f" s.value = '{case}'; s.dispatchEvent(new Event('change'));"
        f" const m = document.querySelector('input[data-mode={mode}]'); m.checked = true;"
        " m.dispatchEvent(new Event('change', { bubbles: true })); })()"
    )
    page.wait_for(
        f"document.getElementById('view3d').dataset.case === '{case}' && "
        f"document.getElementById('view3d').dataset.mode === '{mode}'"
    )
    drawn_after(page, before)


def test_the_3d_view_of_the_paper_cube_in_chromium(paper_cube, tmp_path):
    ps = paper_cube["parameter_set_id"]
    url = paper_cube["url"]
    with browser.Browser(timeout=60) as page:
        page.open(f"{url}/#/calibrations/{paper_cube['calibration']['id']}")
        page.viewport(1280, 1150)
        page.wait_for(f"document.querySelector('#parameters a[href=\"#/parameter-sets/{ps}/3d\"]')")
        page.js(
            f"document.querySelector('#parameters a[href=\"#/parameter-sets/{ps}/3d\"]').click()"
        )
        page.wait_for(
            "document.getElementById('view3d') && document.getElementById('view3d').dataset.ready"
        )
        facts = page.js("document.getElementById('view3d-facts').textContent")
        calibration = paper_cube["calibration"]["result"]
        assert f"{calibration['relative_discrepancy'][0]:.2f}% relative discrepancy" in facts
        names = page.js(
            "[...document.querySelectorAll('#view3d-case option')].map(o => o.textContent)"
        )
        assert names == ["0.25 N (fitted)", "0.5 N (fitted)", "1 N (fitted)"]
        ticks = page.js(
            "[...document.querySelectorAll('#view3d-legend [data-tick]')].map(t => t.textContent)"
        )
        assert ticks[0] == "0 m0.0%" and ticks[-1].endswith("%") and " m" in ticks[-1]

        shots = {}
        for case in (0, 2):
            show_case(page, case)
            shots[case] = canvas_pixels(page, page.screenshot(tmp_path / f"case{case}.png"))
        pixels = shots[0]
        distinct = len(np.unique(pixels.reshape(-1, 3), axis=0))
        drawn = (np.abs(pixels.astype(int) - 255).sum(axis=2) > 30).mean()
        assert distinct > 200 and drawn > 0.1, (distinct, drawn)  # not blank
        bins = hues(pixels)
        many = sorted(b for b, n in bins.items() if n > 40)
        # viridis: purple, blue, teal-green and yellow-green hues (plus the loads' markers)
        assert len(many) >= 4, bins
        assert {b for b in many if 6 <= b <= 10} and {b for b in many if 1 <= b <= 5}, bins
        changed = (np.abs(shots[0].astype(int) - shots[2].astype(int)).sum(axis=2) > 30).mean()
        assert changed > 0.01, changed  # 1 N pulls the top up four times as far as 0.25 N

        show_case(page, 2, "both")  # FEM lines over the FPM surface
        both = canvas_pixels(page, page.screenshot(tmp_path / "both.png"))
        assert (np.abs(both.astype(int) - shots[2].astype(int)).sum(axis=2) > 30).mean() > 0.002
        assert page.console_errors() == []
        copy_to = os.environ.get("FPM_WEB_SCREENSHOT_3D")
        if copy_to:  # the README's picture: 1 N, both shapes, displacements doubled
            before = frames(page)
            page.js(
                "(() => { const s = document.getElementById('view3d-scale');"
                " s.value = '2'; s.dispatchEvent(new Event('change')); })()"
            )
            drawn_after(page, before)
            shutil.copyfile(page.screenshot(tmp_path / "docs.png"), copy_to)


def test_the_parameter_set_pages_link_the_3d_view(paper_cube):
    ps = paper_cube["parameter_set_id"]
    dom = browser.dump_dom(f"{paper_cube['url']}/#/parameter-sets/{ps}")
    assert f'href="#/parameter-sets/{ps}/3d"' in dom
    listing = browser.dump_dom(f"{paper_cube['url']}/#/parameter-sets")
    assert f'href="#/parameter-sets/{ps}/3d"' in listing
