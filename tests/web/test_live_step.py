"""The web view's live model in headless Chromium: service/static/web/fpm-step.js steps the JSON
export as fpm.runtime.Runtime does (positions within 1e-9 of the largest displacement over 1,000
steps with forces that change every step, on the paper's cube and on a voxel organ), and the Web
Worker around it (live-worker.js) answers pushes and drags with moved positions.

The page, the web view's files and the exports come from a small HTTP server of the test's own
(tests/live_page.py: module workers need an http origin). Skipped, with the reason, only where no
Chromium can be had (tests/browser.py installs Debian's when it is missing).
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import browser
import live_page
import numpy as np
import pytest

from fpm.runtime import Runtime

STEPS = 1000
CHECKPOINTS = (1, 10, 100, 500, 1000)
ORGAN_H = 0.006
"""The organ's spacing for the agreement test, m (2,820 nodes: Runtime's 1,000 steps in ~4 s)."""
CONFORMING_H = 0.012
"""The 480-tetrahedron organ's conforming lattice spacing, m (439 nodes)."""
LOADED = 944
"""A loaded node of the cube (top face, load case 0)."""

STEPPER = """async (name, steps, checkpoints, gravity) => {
  const doc = await (await fetch('/data/' + name)).json();
  if (gravity) doc.parameters.gravity = gravity;
  const m = fpm.FpmModel.fromExport(doc, {damping: "kernel"});
  const base = doc.load_cases.map((_, c) => m.loadCaseForces(doc, c));
  const f = new Float64Array(3 * m.nNodes);
  const out = [];
  for (let n = 0; n < steps; n++) {
    f.fill(0);
    base.forEach((b, c) => {
      const s = Math.sin(Math.PI * n / (200 + 70 * c) + c);
      for (let k = 0; k < f.length; k++) f[k] += b[k] * s;
    });
    m.step(f);
    if (checkpoints.includes(n + 1)) {
      out.push({step: n + 1, x: Array.from(m.x), unbalanced: m.unbalanced, settled: m.settled});
    }
  }
  return out;
}"""
"""Steps an export under the forces of :func:`forces_at` and returns the states at checkpoints.

At the kernel's d: the engine's is about four times lighter, and under these forces (the sum of
the load cases, reversing) the lightly damped cube passes near a bifurcation that amplifies a
difference of 1e-12 m to about 1e-3 m in NumPy alone, so two correct ports of the step could not
agree to 1e-9 there; which d and dt the default picks is checked on its own."""


def forces_at(base: list[np.ndarray], n: int) -> np.ndarray:
    """Step n's forces: each load case c times sin(pi n / (200 + 70 c) + c), as STEPPER's."""
    total: Any = 0
    for c, b in enumerate(base):
        total = total + b * math.sin(math.pi * n / (200 + 70 * c) + c)
    return np.asarray(total)


def call(page: browser.Browser, function: str, *args: Any) -> Any:
    """``function`` (JavaScript source) called in the page with JSON ``args``; its value."""
    return page.js(f"({function})(...{json.dumps(args)})")


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The exports, as the page fetches them: cube.json, organ.json, conforming.json (the
    tetrahedral organ's conforming lattice), box.json (springs only)."""
    folder = tmp_path_factory.mktemp("live")
    (folder / "cube.json").write_text(json.dumps(live_page.cube_export()))
    (folder / "organ.json").write_text(json.dumps(live_page.organ_export(ORGAN_H)))
    conforming = live_page.exported(live_page.conforming_spec(CONFORMING_H))
    (folder / "conforming.json").write_text(json.dumps(conforming))
    hat = live_page.conforming_spec(CONFORMING_H)
    hat["fpm"]["loads"] = "hat"
    (folder / "hat.json").write_text(json.dumps(live_page.exported(hat)))
    spec = json.loads((live_page.ROOT / "examples/small-box.json").read_text())
    spec["fpm"] = {"stiffness": "single"}
    box = live_page.exported(spec)
    assert box["volume_stiffness"] is None
    (folder / "box.json").write_text(json.dumps(box))
    return folder


@pytest.fixture(scope="module")
def page(data: Path) -> Iterator[browser.Browser]:
    """Headless Chromium on the blank page with fpm-step.js imported as ``window.fpm``."""
    path, why = browser.chromium()
    if path is None:
        pytest.skip(why)
    with live_page.serve(data) as base, browser.Browser(timeout=120) as b:
        live_page.open_live_page(b, base)
        yield b
        assert b.console_errors() == []


def load(data: Path, name: str) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads((data / name).read_text())
    return doc


# --- The step -------------------------------------------------------------------------------------


def test_forces_equal_the_runtime_s(page, data):
    """Springs and volume term at displaced positions: Runtime.internal_forces to 1e-12."""
    doc = load(data, "cube.json")
    rt = Runtime.from_export(doc)
    x = rt.rest + 0.05 * doc["h"] * np.random.default_rng(1).standard_normal(rt.rest.shape)
    got = call(
        page,
        """async (x) => {
          const doc = await (await fetch('/data/cube.json')).json();
          const m = fpm.FpmModel.fromExport(doc);
          return Array.from(m.internalForces(Float64Array.from(x)));
        }""",
        x.ravel().tolist(),
    )
    expected = rt.internal_forces(x)
    assert np.abs(np.reshape(got, (-1, 3)) - expected).max() <= 1e-12 * np.abs(expected).max()


def test_the_default_damping_is_the_export_s_engine_block_as_the_runtime_s(page, data):
    """Unset, the model steps at parameters.engine's d and dt, as Runtime.from_export does;
    "kernel" at parameters.d and dt; "engine" on an export without the block is refused."""
    doc = load(data, "cube.json")
    got = call(
        page,
        """async () => {
          const doc = await (await fetch('/data/cube.json')).json();
          const pick = (options) => {
            const m = fpm.FpmModel.fromExport(doc, options);
            return [m.d, m.dt, m.damping];
          };
          delete doc.parameters.engine;
          let refused = "";
          try { fpm.FpmModel.fromExport(doc, {damping: "engine"}); }
          catch (e) { refused = e.message; }
          return [pick(), pick({damping: "kernel"}), refused];
        }""",
    )
    engine, p = doc["parameters"]["engine"], doc["parameters"]
    rt = Runtime.from_export(doc)
    assert rt.damping == "engine" and (rt.d, rt.dt) == (engine["d"], engine["dt"])
    assert got[0][:2] == [p["d"], p["dt"]] and got[0][2] == "kernel"  # the block deleted
    assert got[1] == [p["d"], p["dt"], "kernel"]
    assert "no parameters.engine block" in got[2]
    default = call(
        page,
        """async () => {
          const m = fpm.FpmModel.fromExport(await (await fetch('/data/cube.json')).json());
          return [m.d, m.dt, m.damping];
        }""",
    )
    assert default == [engine["d"], engine["dt"], "engine"]


@pytest.mark.parametrize(
    ("name", "gravity"),
    [("cube.json", None), ("organ.json", [0.0, 0.0, -9.81]), ("conforming.json", None)],
)
def test_steps_agree_with_the_runtime(page, data, name, gravity):
    """1,000 steps, forces changing every step (and gravity on the organ): the same positions
    within 1e-9 of the largest displacement, the same unbalanced force and settled flag, and
    the fixed nodes where they were."""
    doc = load(data, name)
    if gravity:
        doc = copy.deepcopy(doc)
        doc["parameters"]["gravity"] = gravity
    states = call(page, STEPPER, name, STEPS, list(CHECKPOINTS), gravity)
    assert [s["step"] for s in states] == list(CHECKPOINTS)
    rt = Runtime.from_export(doc, damping="kernel")
    base = [rt.load_case_forces(doc, c) for c in range(len(doc["load_cases"]))]
    worst = 0.0
    for n in range(STEPS):
        rt.step(forces_at(base, n))
        if n + 1 in CHECKPOINTS:
            state = states[CHECKPOINTS.index(n + 1)]
            x = np.reshape(state["x"], (-1, 3))
            scale = np.abs(rt.x - rt.rest).max()
            assert scale > 0
            error = np.abs(x - rt.x).max() / scale
            worst = max(worst, error)
            assert error <= 1e-9, (n + 1, error)
            assert np.array_equal(x[rt.fixed], rt.rest[rt.fixed])
            assert state["unbalanced"] == pytest.approx(rt.unbalanced, rel=1e-6)
            assert state["settled"] == rt.settled
    print(f"{name}: {rt.n_nodes} nodes, largest difference {worst:.1e} of the displacement")


def test_settles_where_the_runtime_settles(page, data):
    """A constant load case run to settling: the same steps (to one) and the same state."""
    doc = load(data, "cube.json")
    got = call(
        page,
        """async () => {
          const doc = await (await fetch('/data/cube.json')).json();
          const m = fpm.FpmModel.fromExport(doc);
          const steps = m.run(m.loadCaseForces(doc, 1), 20000);
          return {steps, settled: m.settled, x: Array.from(m.x)};
        }""",
    )
    rt = Runtime.from_export(doc)
    steps = rt.run(rt.load_case_forces(doc, 1), max_steps=20_000)
    assert rt.settled and got["settled"] and abs(got["steps"] - steps) <= 1
    u = rt.x - rt.rest
    assert np.abs(np.reshape(got["x"], (-1, 3)) - rt.x).max() <= 1e-9 * np.abs(u).max()


def test_a_spring_only_export(page, data):
    """No volume term (volume_stiffness null): springs alone, as Runtime steps them."""
    doc = load(data, "box.json")
    states = call(page, STEPPER, "box.json", 300, [300], None)
    rt = Runtime.from_export(doc, damping="kernel")
    base = [rt.load_case_forces(doc, c) for c in range(len(doc["load_cases"]))]
    for n in range(300):
        rt.step(forces_at(base, n))
    x = np.reshape(states[0]["x"], (-1, 3))
    assert np.abs(x - rt.x).max() <= 1e-9 * np.abs(rt.x - rt.rest).max()


def test_not_an_export(page):
    answer = page.js(
        "(() => { try { fpm.FpmModel.fromExport({format: 'something else'}); return 'built'; }"
        " catch (e) { return `${e instanceof fpm.ExportFormatError} ${e.message}`; } })()"
    )
    assert answer.startswith("true ") and "fpm-lattice" in answer


# --- The worker -----------------------------------------------------------------------------------

WORKER = """(source) => new Promise((resolve, reject) => {
  const w = new Worker('/web/live-worker.js', {type: 'module'});
  window.live = {worker: w, frames: [], errors: [], ready: null};
  w.onerror = (e) => reject(new Error('worker: ' + (e.message || 'failed to start')));
  w.onmessage = (e) => {
    const m = e.data;
    if (m.type === 'ready') {
      window.live.ready = m;
      resolve({nodes: m.nodes, dt: m.dt, d: m.d, damping: m.damping});
    }
    else if (m.type === 'frame') window.live.frames.push(m);
    else if (m.type === 'error') {
      window.live.errors.push(m.message);
      reject(new Error(m.message));
    }
  };
  if (source.bufferOf) {  // the export's bytes, fetched here and transferred
    fetch(source.bufferOf).then(r => r.arrayBuffer())
      .then(buffer => w.postMessage({type: 'load', buffer}, [buffer]));
  } else w.postMessage({type: 'load', ...source});
})"""
"""Starts live-worker.js in the page (window.live) and waits for its ``ready``."""


LAST = "live.frames[live.frames.length - 1]"


def send(page: browser.Browser, message: dict[str, Any]) -> None:
    """Post ``message`` to the page's worker."""
    page.js(f"live.worker.postMessage({json.dumps(message)})")


def last_frame(page: browser.Browser) -> dict[str, Any]:
    frame: dict[str, Any] = page.js(
        "(() => { const f = live.frames[live.frames.length - 1]; return {steps: f.steps,"
        " settled: f.settled, unbalanced: f.unbalanced, n: live.frames.length,"
        " positions: Array.from(f.positions), isFloat32: f.positions instanceof Float32Array}; })()"
    )
    return frame


def test_the_worker_answers_a_push_and_a_drag(page, data):
    """A push moves the pushed node along the force; positions come back as Float32Arrays;
    a drag pulls a node toward the pointer; let go, the model settles back and stops."""
    doc = load(data, "cube.json")
    started = call(page, WORKER, {"url": "/data/cube.json"})
    engine = doc["parameters"]["engine"]
    assert started["nodes"] == 1000 and started["damping"] == "engine"
    assert (started["dt"], started["d"]) == (engine["dt"], engine["d"])
    rest = np.asarray(doc["nodes"])
    send(page, {"type": "push", "node": LOADED, "force": [0, 0, 0.25]})
    above = float(rest[LOADED, 2]) + 1e-5
    page.wait_for(f"live.frames.length > 0 && {LAST}.positions[{3 * LOADED + 2}] > {above!r}")
    frame = last_frame(page)
    assert frame["isFloat32"] and frame["steps"] > 0
    moved = np.reshape(frame["positions"], (-1, 3)) - rest
    assert moved[LOADED, 2] > 1e-5 and np.abs(moved[LOADED, :2]).max() < moved[LOADED, 2]
    fixed = np.asarray(doc["fixed"])
    assert np.abs(moved[fixed]).max() < 1e-6  # float32 of the rest positions

    # A drag: node 955's handle toward a point 5 mm off along x.
    send(page, {"type": "push", "node": LOADED, "force": None})
    target = rest[955] + [0.005, 0.0, 0.0]
    send(page, {"type": "drag", "node": 955, "target": target.tolist()})
    page.wait_for(f"{LAST}.positions[{3 * 955}] > {float(rest[955, 0]) + 1e-3!r}")
    # Let go: it settles back to rest and the worker stops stepping (a frame after the release:
    # the drag itself may have settled, its last frame still marked so).
    before = page.js("live.frames.length")
    send(page, {"type": "release"})
    page.wait_for(f"live.frames.length > {before} && {LAST}.settled", timeout=60)
    settled = last_frame(page)
    assert np.abs(np.reshape(settled["positions"], (-1, 3)) - rest).max() < 1e-4
    count = settled["n"]
    page.js("new Promise(r => setTimeout(r, 300))")
    assert last_frame(page)["n"] == count  # at rest: no more frames
    assert page.js("live.errors") == []
    page.js("live.worker.terminate()")


def test_the_worker_steps_as_the_model_does(page, data):
    """``step`` messages: the worker's positions are the model's (as float32), and a push held
    over steps is the same constant force (the export handed over as bytes this time)."""
    call(page, WORKER, {"bufferOf": "/data/cube.json"})
    got = page.js(
        """(async () => {
          const w = live.worker;
          w.postMessage({type: 'pause'});
          w.postMessage({type: 'push', node: NODE, force: [0.01, -0.02, 0.3]});
          w.postMessage({type: 'step', count: 150});
          const stepped = () => live.frames.find(f => f.stepsThisFrame === 150);
          while (!stepped()) await new Promise(r => setTimeout(r, 10));
          const frame = stepped();
          const doc = await (await fetch('/data/cube.json')).json();
          const m = fpm.FpmModel.fromExport(doc);
          const f = new Float64Array(3 * m.nNodes);
          f.set([0.01, -0.02, 0.3], 3 * NODE);
          for (let n = 0; n < 150; n++) m.step(f);
          return {same: Float32Array.from(m.x).every((v, k) => v === frame.positions[k]),
                  steps: frame.steps};
        })()""".replace("NODE", str(LOADED))
    )
    assert got == {"same": True, "steps": 150}
    page.js("live.worker.terminate()")


def test_the_worker_shares_a_push_as_a_hat_fit_did(page, data):
    """An export fitted with ``fpm.loads: "hat"``: a push on a surface node acts as the fit
    applied a force there, shared over the nodes around it (``load_shares``): the worker's
    positions are the model's stepped under :meth:`Runtime.applied` of that push."""
    doc = load(data, "hat.json")
    runtime = Runtime.from_export(doc)
    table = doc["load_shares"]
    node = next(n for n in table["nodes"] if not runtime.fixed[n])
    push = np.zeros((runtime.n_nodes, 3))
    push[node] = [0.001, -0.002, -0.01]
    spread = runtime.applied(push)
    assert np.count_nonzero(np.any(spread != 0, axis=1)) >= 4  # shared, not at the node alone
    call(page, WORKER, {"url": "/data/hat.json"})
    got = call(
        page,
        """async (node, force, spread) => {
          const w = live.worker;
          w.postMessage({type: 'pause'});
          w.postMessage({type: 'push', node, force});
          w.postMessage({type: 'step', count: 150});
          const stepped = () => live.frames.find(f => f.stepsThisFrame === 150);
          while (!stepped()) await new Promise(r => setTimeout(r, 10));
          const doc = await (await fetch('/data/hat.json')).json();
          const m = fpm.FpmModel.fromExport(doc);
          const f = Float64Array.from(spread);
          for (let n = 0; n < 150; n++) m.step(f);
          return {model: Array.from(m.x), worker: Array.from(stepped().positions)};
        }""",
        node,
        push[node].tolist(),
        spread.ravel().tolist(),
    )
    rest = np.asarray(doc["nodes"]).ravel()
    moved = np.abs(np.asarray(got["model"]) - rest).max()
    assert moved > 1e-6
    assert np.abs(np.asarray(got["worker"]) - np.float32(got["model"])).max() <= 1e-6 * moved
    page.js("live.worker.terminate()")


def test_the_worker_waits_out_a_202(page, data):
    """A URL that answers 202 (the export being made) first: the worker asks again."""
    started = call(page, WORKER, {"url": "/later/box.json"})
    assert started["nodes"] == len(load(data, "box.json")["nodes"])
    page.js("live.worker.terminate()")


def test_a_far_drag_is_capped_so_the_engine_step_stays_finite(page, data):
    """A drag's default cap is 0.5 m L / dt^2 (L the node's shortest spring); a pull toward a
    target 20 spacings away at the engine's dt, so capped, settles with finite positions (the
    uncapped pull of the node's own stiffness diverges)."""
    doc = load(data, "cube.json")
    got = call(
        page,
        """async (node) => {
          const doc = await (await fetch('/data/cube.json')).json();
          const m = fpm.FpmModel.fromExport(doc);
          const limit = m.stepForceLimit(), k = m.nodeStiffness()[node];
          const run = (cap) => {
            m.reset();
            const f = new Float64Array(3 * m.nNodes);
            const target = m.rest[3 * node + 2] + 20 * doc.h;
            for (let n = 0; n < 3000; n++) {
              f[3 * node + 2] = Math.min(k * (target - m.x[3 * node + 2]), cap);
              m.step(f);
            }
            return [m.x.every(Number.isFinite), m.settled];
          };
          return {limit: Array.from(limit), capped: run(limit[node]), free: run(Infinity)};
        }""",
        LOADED,
    )
    rt = Runtime.from_export(doc)
    springs = np.asarray(doc["springs"])
    shortest = np.full(rt.n_nodes, np.inf)
    for end in (0, 1):
        np.minimum.at(shortest, springs[:, end].astype(int), springs[:, 2])
    expected = 0.5 * rt.masses * shortest / rt.dt**2
    np.testing.assert_allclose(got["limit"], expected, rtol=1e-12)
    assert got["capped"] == [True, True]
    assert got["free"][0] is False
