"""The web view's live model: steps per second of fpm-step.js in headless Chromium.

The JSON export stepped as the browser steps it (fpm.runtime's step in JavaScript, float64 typed
arrays): families+volume at the continuum start, dt auto, a force on the loaded node that changes
every step (as a pointer's push does), on

1. the paper's cube (examples/paper-material-a.json, 10^3 nodes). Goal: >= 1,000 steps/s, a
   haptic loop's rate;
2. the voxel organ (bench/organ.py) at h = 3 mm (19,692 nodes). Goal: >= 60 steps/s, one step
   per frame of the 3D view at least.

Each in the page's main thread and in the Web Worker (live-worker.js, ``step`` messages timed in
the worker), best of 3 runs. "x real time" is the simulated time per second of wall time (steps/s
times dt): the fitted dt is small, so the live model runs in slow motion where that is under 1.
The export is served by a small HTTP server of our own (tests/live_page.py); Chromium is Debian's
(tests/browser.py installs it when missing; without one the bench says so and skips).
Run: ``python -m bench live`` or ``python -m bench.bench_live``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
ORGAN_H = 0.003
CUBE_STEPS, ORGAN_STEPS = 3000, 300
GOALS = {"cube": 1000.0, "organ": 60.0}
"""Steps per second the JavaScript step should reach."""

PAGE_RUN = """async (name, steps) => {
  const doc = await (await fetch('/data/' + name)).json();
  const m = fpm.FpmModel.fromExport(doc);
  const f = m.loadCaseForces(doc, 0);
  const node = doc.load_cases[0].nodes[0];
  const f0 = f.slice(3 * node, 3 * node + 3);
  const run = (count) => {
    for (let n = 0; n < count; n++) {
      const s = 1 + 0.5 * Math.sin(0.01 * n);
      f[3 * node] = s * f0[0]; f[3 * node + 1] = s * f0[1]; f[3 * node + 2] = s * f0[2];
      m.step(f);
    }
  };
  run(Math.min(steps, 200));  // compiled
  let best = Infinity;
  for (let r = 0; r < 3; r++) {
    const t0 = performance.now();
    run(steps);
    best = Math.min(best, performance.now() - t0);
  }
  return {ms: best / steps, nodes: m.nNodes, springs: m.nSprings, hexahedra: m.nHexahedra,
          dt: m.dt, moved: m.x.some((v, k) => v !== m.rest[k])};
}"""

WORKER_RUN = """(name, steps) => new Promise((resolve, reject) => {
  const w = new Worker('/web/live-worker.js', {type: 'module'});
  const times = [];
  let node = 0;
  w.onmessage = (e) => {
    const m = e.data;
    if (m.type === 'error') { w.terminate(); reject(new Error(m.message)); return; }
    if (m.type === 'ready') {
      w.postMessage({type: 'pause'});
      w.postMessage({type: 'push', node: 0, force: [0, 0, 0]});
      w.postMessage({type: 'step', count: Math.min(steps, 200)});
      return;
    }
    if (m.type !== 'frame' || m.stepsThisFrame === 0) return;
    if (m.stepsThisFrame === steps) times.push(m.ms / steps);
    if (times.length === 3) { w.terminate(); resolve({ms: Math.min(...times)}); return; }
    node = (node + 1) % 4;
    w.postMessage({type: 'push', node, force: [0, 0, 0.01 * (1 + times.length)]});
    w.postMessage({type: 'step', count: steps});
  };
  w.postMessage({type: 'load', url: '/data/' + name});
})"""


def exports(folder: Path) -> dict[str, Any]:
    """Writes cube.json and organ.json into ``folder``; the seconds each export took."""
    from live_page import cube_export, organ_export

    made = {}
    for name, build in (("cube", cube_export), ("organ", lambda: organ_export(ORGAN_H))):
        t0 = time.perf_counter()
        (folder / f"{name}.json").write_text(json.dumps(build()))
        made[name] = time.perf_counter() - t0
    return made


def main() -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    import browser
    import live_page

    print(
        "\nThe live model's step (service/static/web/fpm-step.js) in headless Chromium: "
        "families+volume, dt auto, a changing push; best of 3 runs"
    )
    path, why = browser.chromium()
    if path is None:
        print(f"   skipped: {why}")
        return
    version = subprocess.run([path, "--version"], capture_output=True, text=True)
    print(f"   browser: {version.stdout.strip() or path}")
    failures: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        folder = Path(tmp)
        exports(folder)
        rows = []
        with live_page.serve(folder) as base, browser.Browser(timeout=600) as page:
            live_page.open_live_page(page, base)
            for name, steps in (("cube", CUBE_STEPS), ("organ", ORGAN_STEPS)):
                args = json.dumps([f"{name}.json", steps])
                main_thread = page.js(f"({PAGE_RUN})(...{args})")
                worker = page.js(f"({WORKER_RUN})(...{args})")
                assert main_thread["moved"]
                rows.append((name, main_thread, worker))
            errors = page.console_errors()
    print(
        f"{'model':>6} {'nodes':>7} {'springs':>8} {'hexahedra':>9} {'where':>7} {'ms/step':>8} "
        f"{'steps/s':>8} {'goal':>6} {'ratio':>6} {'x real time':>11}"
    )
    for name, main_thread, worker in rows:
        goal = GOALS[name]
        for where, ms in (("page", main_thread["ms"]), ("worker", worker["ms"])):
            rate = 1e3 / ms
            ok = rate >= goal
            print(
                f"{name:>6} {main_thread['nodes']:>7,} {main_thread['springs']:>8,} "
                f"{main_thread['hexahedra']:>9,} {where:>7} {ms:>8.3f} {rate:>8,.0f} "
                f"{goal:>6,.0f} {rate / goal:>6.2f} {rate * main_thread['dt']:>11.2f}  "
                f"{'met' if ok else 'NOT met'}"
            )
            if not ok:
                failures.append(f"{name} in the {where}: {rate:.0f} steps/s < {goal:.0f}")
    if errors:
        failures.append("console errors: " + "; ".join(errors))
    print("\ngoals: " + ("all met" if not failures else "MISSED " + "; ".join(failures)))


if __name__ == "__main__":
    main()
