"""The native step (fpm/native/fpm_step.c) against the NumPy runtime and a memory-stream bound.

Lattices: boxes at the paper's cube's spacing (h = 0.1/9 m, material A, full connectivity, the
bottom held), the default model (families+volume at the continuum start), dt auto, d = 0.5
sqrt(E h m): 10^3 = 1,000 nodes (the paper's cube), 13^3 = 2,197, 27^3 = 19,683 and 47^3 =
103,823 nodes. Built straight from the box's problem (springs, masses, hexahedra, kappa, rest
volumes: the JSON export's arrays; no calibration, no export's settle modes), stepped under a
push on the top centre node that changes every step.

Per lattice: steps/s of the native float64 step timed from C as an engine calls it
(bench/step_loop.c: no Python between steps; its default threads: OpenMP's from
FPM_THREAD_NODES nodes, one below), the same step from Python (``Runtime.step``: ctypes and the
array checks added), the float32 step and the NumPy runtime from Python; the stream
bound: the seconds of a loop reading the bytes the step reads and writes once per step (model
arrays and state, bench/stream.c, same compiler, flags and threads), measured in the same run;
the ratio C loop / stream (1 = at the bound). The wall clock of a shared machine: the load
average is recorded beside, and the CPU seconds of the native step per step as well.

Goals (the C loop): >= 20,000 steps/s at about 2,000 nodes, >= 1,000 at about 20,000, >= 150
at about 100,000; within 2x of the stream bound; >= 20x the NumPy runtime.

Part ``damping``: the paper's cube (material A's forces) calibrated with the default model
(two-stage, families+volume, dt auto), its JSON export stepped by the C step per load case from
rest until settled (the export's criterion), at the fitted d and dt (the calibration kernel's)
and at :mod:`fpm.dynamics.engine_damping`'s d and dt (the all-at-once step's): the steps and the
simulated seconds each takes, and how far apart the two settled states are. Goal: fewer steps
with the engine's d in every load case.

Part ``probe``: a probe at 1 kHz on the voxel organ (:func:`probe_part`).

Part ``depth``: microseconds a step and the unseen presses' discrepancy at every depth, on the
paper's cube and the voxel organ (:func:`depth_part`).

Run: ``python -m bench native`` (about 4 minutes); ``BENCH_NATIVE_PARTS=damping`` for one part.
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import results

ROOT = Path(__file__).resolve().parents[1]
SIDES = tuple(int(s) for s in os.environ.get("BENCH_SIDES", "10,13,27,47").split(","))
H = 0.1 / 9
GOALS = {13: 20_000.0, 27: 1_000.0, 47: 150.0}
"""Nodes per side -> native steps/s goal."""
STREAM_GOAL, NUMPY_GOAL = 2.0, 20.0
SECONDS = 1.5
"""Wall seconds each timed loop runs for (at least 20 steps)."""


def box_runtime(side: int, backend: str, precision: str = "float64") -> tuple[Any, np.ndarray]:
    """(Runtime, (N, 3) push) of the box with ``side`` nodes per edge."""
    size = H * (side - 1)
    centre = H * ((side - 1) // 2)
    spec = {
        "name": f"box {side}^3",
        "material": {"youngs_modulus": 10_000.0, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {"type": "box", "size": [size] * 3, "nodes": [side] * 3,
                     "connectivity": "full"},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"name": "push", "forces": [{"at": [centre, centre, size],
                                                    "vector": [0.0, 0.0, -0.5]}]}],
        "fpm": {"stiffness": "families+volume"},
    }  # fmt: skip
    return spec_runtime(spec, backend, precision)


def spec_runtime(
    spec: dict[str, Any], backend: str, precision: str = "float64"
) -> tuple[Any, np.ndarray]:
    """(Runtime, (N, 3) forces of the first load case) of ``spec``'s lattice at the continuum
    start of families+volume, dt auto, d = 0.5 sqrt(E h m): the JSON export's arrays, built
    without an export."""
    from fpm import load_problem
    from fpm.fitting.step_budget import runtime_of
    from fpm.model.stiffness import continuum_start, model_stiffness

    problem = load_problem({**spec, "fpm": {"stiffness": "families+volume"}})
    stiffness = model_stiffness(problem, continuum_start(problem))
    e = problem.spec.material.youngs_modulus
    d = 0.5 * float(np.sqrt(e * problem.h * problem.solid.masses.mean()))
    rt = runtime_of(problem, stiffness, d, None, backend, precision)
    push = problem.load_cases[0].dense(problem.n_nodes)
    return rt, push


def changing_pushes(push: np.ndarray, dtype: Any) -> np.ndarray:
    """(16, N, 3) ``push`` scaled by 1 + sin, one a step, so that the forces change every step."""
    return np.ascontiguousarray([push * (1.0 + 0.5 * np.sin(0.01 * n)) for n in range(16)],
                                dtype=dtype)  # fmt: skip


def steps_per_second(rt: Any, push: np.ndarray) -> tuple[float, float]:
    """(steps/s over wall time, CPU seconds per step) of ``rt`` under a push that changes
    every step."""
    pushes = list(changing_pushes(push, rt.x.dtype))
    for p in pushes[:4]:
        rt.step(p)
    count, steps = 20, 0
    wall = cpu = 0.0
    while wall < SECONDS:
        t0, c0 = time.perf_counter(), time.process_time()
        for n in range(count):
            rt.step(pushes[n % 16])
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        steps += count
        count *= 2
    return steps / wall, cpu / steps


def step_bytes(rt: Any) -> int:
    """Bytes the native step reads and writes once per step: the state (x read, x_next
    written, v read and written, forces read), per node rest, m g, dt/m, the damping
    denominator, the fixed flag and two row offsets; per spring end the neighbour, rest length
    and stiffness; per hexahedron its corners, kappa, rest volume, its corner forces written
    and read and their slots."""
    real = np.dtype(rt.x.dtype).itemsize
    n, s, h = rt.n_nodes, len(rt.springs), len(rt.hexahedra)
    per_node = (3 + 3 + 6 + 3) * real + (3 + 3 + 1 + 1) * real + 1 + 8
    per_spring = 2 * (4 + 2 * real)
    per_hex = 8 * 4 + 2 * real + 2 * 24 * real + 8 * 4
    return n * per_node + s * per_spring + h * per_hex


def stream_library() -> ctypes.CDLL:
    """bench/stream.c and bench/step_loop.c (with fpm_step.c) compiled as the native step is
    (flags, OpenMP), into its cache."""
    from fpm import native

    cc = native.compiler()
    if cc is None:
        raise native.CompilerUnavailable("no C compiler")
    here = Path(__file__).parent
    sources = [here / "stream.c", here / "step_loop.c", native.SOURCE]
    newest = max(source.stat().st_mtime for source in [*sources, native.HEADER])
    target = native.cache_dir() / f"bench_loops{native._suffix()}"
    if not target.exists() or target.stat().st_mtime < newest:
        target.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [cc, *native.FLAGS, "-fopenmp", f"-I{native.HERE}", *map(str, sources), "-o",
             str(target), "-lm"],
            check=True, capture_output=True,
        )  # fmt: skip
    lib = ctypes.CDLL(str(target))
    lib.stream_pass.restype = ctypes.c_double
    lib.stream_pass.argtypes = [ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_long]
    lib.step_seconds.restype = ctypes.c_double
    lib.step_seconds.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p, ctypes.c_long,
                                 ctypes.c_long, ctypes.c_int]  # fmt: skip
    return lib


def c_loop_seconds(lib: ctypes.CDLL, rt: Any, push: np.ndarray, threads: int) -> float:
    """Seconds per float64 step of ``rt``'s lattice stepped from C (bench/step_loop.c) under
    16 pushes that change every step, best of 5 rounds of about 0.1 s."""
    from fpm.native import runtime_bytes

    data = runtime_bytes(rt)
    pushes = changing_pushes(push, np.float64)
    steps = 20
    while True:
        t0 = time.perf_counter()
        lib.step_seconds(data, len(data), pushes.ctypes.data, 16, steps, threads)
        if time.perf_counter() - t0 > 0.1:
            break
        steps *= 2
    best = min(lib.step_seconds(data, len(data), pushes.ctypes.data, 16, steps, threads)
               for _ in range(5))  # fmt: skip
    if best < 0:
        raise RuntimeError("bench/step_loop.c could not load the binary export")
    return best


def stream_seconds(lib: ctypes.CDLL, nbytes: int, threads: int) -> float:
    """Seconds per pass over ``nbytes`` (best of 5 rounds of passes lasting about 0.1 s)."""
    data = np.random.default_rng(0).random(max(1, nbytes // 8))
    passes = 1
    while True:
        t0 = time.perf_counter()
        lib.stream_pass(data.ctypes.data, len(data), threads, passes)
        if time.perf_counter() - t0 > 0.1:
            break
        passes *= 2
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        lib.stream_pass(data.ctypes.data, len(data), threads, passes)
        best = min(best, (time.perf_counter() - t0) / passes)
    return best


def damping_part() -> None:
    """Part ``damping`` (the module docstring)."""
    import json

    from bench.organ import ellipsoid_spec
    from fpm import calibrate, load_problem
    from fpm.io.export import export

    cube = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    cube["fpm"] = {"stiffness": "families+volume"}
    for name, spec in (("paper's cube", cube), ("voxel organ h 7 mm", ellipsoid_spec(0.007))):
        problem = load_problem(spec)
        t0 = time.perf_counter()
        result = calibrate(problem)
        print(f"{name} calibrated in {time.perf_counter() - t0:.1f} s", flush=True)
        doc = json.loads(export(problem, result.to_dict(), "json"))
        settle_runs(name, doc)


def settle_runs(name: str, doc: dict[str, Any]) -> None:
    """Part ``damping``'s runs on one export ``doc``: each load case from rest until settled at
    the fitted (kernel's) d and dt and at the engine's."""
    from fpm.dynamics.engine_damping import with_engine_damping
    from fpm.runtime import Runtime

    kernel = Runtime.from_export(doc, backend="native", damping="kernel")
    engine, found = with_engine_damping(kernel)
    print(
        f"kernel d {kernel.d:.4g} N s/m at dt {kernel.dt * 1e3:.4g} ms; engine d {found.d:.4g} "
        f"at dt {found.dt * 1e3:.4g} ms (w {found.omega_min:.4g}..{found.omega_max:.4g} rad/s)"
    )
    print(
        f"{'load case':>20} {'kernel d':>9} {'engine d':>9} {'ratio':>6} {'sim s':>13} {'apart':>8}"
    )
    cap = int(doc["parameters"]["max_steps"]) * 20
    for j, case in enumerate(doc["load_cases"]):
        push = kernel.load_case_forces(doc, j)
        kernel.reset()
        engine.reset()
        slow, fast = kernel.run(push, cap), engine.run(push, cap)
        u = np.abs(kernel.x - kernel.rest).max()
        apart = float(np.abs(engine.x - kernel.x).max() / u)
        print(
            f"{case['name']:>20} {slow:>9,} {fast:>9,} {fast / slow:>6.2f} "
            f"{slow * kernel.dt:>6.3f}/{fast * engine.dt:<6.3f} {apart:>8.1e}",
            flush=True,
        )
        results.record(
            "native",
            "damping",
            lattice=name,
            load_case=case["name"],
            kernel_d=kernel.d,
            kernel_dt=kernel.dt,
            kernel_steps=slow,
            kernel_settled=kernel.settled,
            engine_d=found.d,
            engine_dt=found.dt,
            engine_steps=fast,
            engine_settled=engine.settled,
            steps_ratio=fast / slow,
            settled_apart=apart,
            meets_goal=engine.settled and fast < slow,
        )


PROBE_ORGANS = ((0.007, 2000), (0.005, 2000))
"""The voxel organ's spacing h (m) and the 1 ms ticks the probe runs for (2 s). The 20k-node
organ is not run: its engine damping's shift-invert eigensolve alone outlasts the bench's few
minutes on the shared machine."""


def probe_part() -> None:
    """Part ``probe``: a probe pressed into the voxel organ's top (bench/organ.py) and back at
    1 kHz: in over 0.5 s to 0.2 h, held 0.5 s, out over 0.5 s, away 0.5 s; a one-sided penalty
    of 4 times the node's stiffness; the C step at the engine's damping, its dt cut to a whole
    number of steps a millisecond. Per tick the steps and the probe's force, timed: ticks/s
    (goal 1,000: the loop keeps its rate), the 99th percentile of a tick, the ticks over 1 ms;
    the energy's largest rise during the holds (relative to its peak) and at the end."""
    import dataclasses
    import math

    from bench.organ import ellipsoid_spec
    from fpm.dynamics.engine_damping import engine_damping, rest_stiffness

    print(f"{'nodes':>7} {'steps/tick':>10} {'ticks/s':>8} {'p99 ms':>7} {'over 1 ms':>9} "
          f"{'hold rise':>9} {'end':>8} {'load':>5}")  # fmt: skip
    for h, ticks in PROBE_ORGANS:
        load = os.getloadavg()[0]
        base, push = spec_runtime(ellipsoid_spec(h), "native")
        found = engine_damping(base)
        substeps = math.ceil(1e-3 / found.dt)
        rt = dataclasses.replace(base, d=found.d, dt=1e-3 / substeps)
        node = int(np.flatnonzero(np.abs(push).sum(axis=1))[0])
        n = push[node] / np.linalg.norm(push[node])
        block = rest_stiffness(rt)[3 * node : 3 * node + 3, 3 * node : 3 * node + 3]
        k = 4.0 * float(block.diagonal().max())
        depth = 0.2 * h
        forces = np.zeros_like(rt.rest)

        def gap(
            t: float, rt: Any = rt, node: int = node, n: np.ndarray = n, depth: float = depth
        ) -> float:
            tip = depth * min(1.0, t / 0.5, max(0.0, (1.5 - t) / 0.5)) if t < 1.5 else 0.0
            return max(0.0, tip - float((rt.x[node] - rt.rest[node]) @ n))

        times, energy = [], []
        for tick in range(ticks):
            t = (tick + 1) * 1e-3
            t0 = time.perf_counter()
            for _ in range(substeps):
                forces[node] = k * gap(t) * n
                rt.step(forces)
            times.append(time.perf_counter() - t0)
            if ticks >= 2000:
                kinetic = 0.5 * float(np.sum(rt.masses[:, None] * rt.v**2))
                energy.append(kinetic + rt.energy(rt.x) + 0.5 * k * gap(t) ** 2)
        spent = np.array(times)
        rise = end = float("nan")
        if energy:
            e = np.array(energy)
            rise = max(float(np.diff(e[a:b]).max()) for a, b in ((500, 1000), (1500, 2000)))
            rise, end = rise / e.max(), float(e[-1] / e.max())
        rate = 1.0 / spent.mean()
        p99 = float(np.percentile(spent, 99)) * 1e3
        over = int((spent > 1e-3).sum())
        print(f"{rt.n_nodes:>7,} {substeps:>10} {rate:>8,.0f} {p99:>7.2f} {over:>5}/{ticks:<4} "
              f"{rise:>9.1e} {end:>8.1e} {load:>5.2f}", flush=True)  # fmt: skip
        results.record(
            "native",
            "probe",
            h=h,
            nodes=rt.n_nodes,
            ticks=ticks,
            steps_per_tick=substeps,
            dt=rt.dt,
            d=rt.d,
            ticks_per_s=rate,
            p99_tick_ms=p99,
            ticks_over_budget=over,
            hold_energy_rise=rise,
            end_energy=end,
            meets_goal=rate >= 1000.0,
            load_average=load,
        )


DEPTH_CASES = (
    {"name": "sideways", "forces": [{"at": [0.04444, 0.04444, 0.1], "vector": [0.5, 0, 0]}]},
    {"name": "corner", "forces": [{"at": [0.1, 0.1, 0.1], "vector": [0, 0, -0.5]}]},
)
"""The cube's unseen presses for part ``depth``: sideways at the top and down on a corner."""


def depth_part() -> None:
    """Part ``depth``: the paper's Fig. 7 and Table 1 together. The paper's cube (material A,
    the default model, two unseen presses :data:`DEPTH_CASES`) and the voxel organ at h = 7 mm
    (its three unseen presses) calibrated with the defaults; then, at every depth of the
    fitted model, the region step's microseconds (:meth:`fpm.runtime.Runtime.region`, the
    slowest load case, :func:`fpm.fitting.step_budget.step_microseconds`: the native step)
    and the unseen presses' relative discrepancy at that depth (their static equilibria
    against the FEM reference)."""
    import json

    from bench.organ import ellipsoid_spec
    from fpm import calibrate, load_problem, solve_fem
    from fpm.fitting.damping.validation import validate
    from fpm.fitting.step_budget import runtime_of, step_microseconds
    from fpm.model.stiffness import model_stiffness, theta_of

    cube = json.loads((ROOT / "examples/paper-material-a.json").read_text())
    cube["fpm"] = {"stiffness": "families+volume"}
    cube["validation_cases"] = list(DEPTH_CASES)
    organ = ellipsoid_spec(0.007, validation=True)
    print(f"{'lattice':>22} {'depth':>5} {'nodes':>6} {'us/step':>8} {'unseen %':>22}")
    for name, spec in (("paper's cube", cube), ("voxel organ h 7 mm", organ)):
        problem = load_problem(spec)
        reference = solve_fem(problem)
        result = calibrate(problem, reference=reference)
        p = result.parameters
        theta = theta_of(problem, p.k, p.stiffness, p.volume_stiffness)
        whole = runtime_of(problem, model_stiffness(problem, theta), p.d, result.settle.dt)
        cases = [(c.nodes, c.dense(problem.n_nodes)) for c in problem.all_cases]
        for depth in range(1, p.full_depth + 1):
            regions = [(whole.region(nodes, depth), f) for nodes, f in cases]
            if depth > 1 and all(r.layers < depth - 1 for r, _ in regions):
                break  # every list ended a layer ago: deeper is the same model
            us = max(step_microseconds(r.runtime, r.forces(f)) for r, f in regions)
            nodes = max(len(r.nodes) for r, _ in regions)
            at = None if depth >= p.full_depth else depth
            unseen = validate(problem, reference, theta, at, geometry=False).relative
            print(f"{name:>22} {depth:>5} {nodes:>6,} {us:>8.1f} "
                  f"{' / '.join(f'{u:.1f}' for u in unseen):>22}", flush=True)  # fmt: skip
            results.record(
                "native",
                "depth",
                lattice=name,
                lattice_nodes=problem.n_nodes,
                depth=depth,
                full_depth=p.full_depth,
                fitted_depth=p.depth,
                region_nodes=nodes,
                us_per_step=us,
                unseen_relative=unseen,
                worst_unseen=max(unseen),
                backend=whole.backend_used,
                load_average=os.getloadavg()[0],
            )


def main() -> None:
    parts = os.environ.get("BENCH_NATIVE_PARTS", "steps,damping,probe,depth").split(",")
    if "probe" in parts:
        probe_part()
    if "steps" in parts:
        steps_part()
    if "damping" in parts:
        damping_part()
    if "depth" in parts:
        depth_part()


def steps_part() -> None:
    """Part ``steps`` (the module docstring)."""
    lib = stream_library()
    print(
        f"{'nodes':>8} {'springs':>9} {'C loop/s':>9} {'goal':>7} {'python/s':>9} "
        f"{'f32/s':>9} {'numpy/s':>8} {'x numpy':>8} {'stream/s':>9} {'x stream':>8} "
        f"{'cpu us':>7} {'load':>5}"
    )
    for side in SIDES:
        load = os.getloadavg()[0]
        rt, push = box_runtime(side, "native")
        threads = rt._engine.thread_count
        c_rate = 1.0 / c_loop_seconds(lib, rt, push, threads)
        native_rate, cpu = steps_per_second(rt, push)
        f32, push32 = box_runtime(side, "native", "float32")
        f32_rate, _ = steps_per_second(f32, push32)
        numpy_rt, _ = box_runtime(side, "numpy")
        numpy_rate, _ = steps_per_second(numpy_rt, push)
        nbytes = step_bytes(rt)
        stream = stream_seconds(lib, nbytes, threads)
        ratio = 1.0 / c_rate / stream
        goal = GOALS.get(side)
        print(
            f"{rt.n_nodes:>8,} {len(rt.springs):>9,} {c_rate:>9,.0f} {goal or 0:>7,.0f} "
            f"{native_rate:>9,.0f} {f32_rate:>9,.0f} {numpy_rate:>8,.1f} "
            f"{c_rate / numpy_rate:>8.1f} {1 / stream:>9,.0f} {ratio:>8.2f} "
            f"{cpu * 1e6:>7.0f} {load:>5.2f}",
            flush=True,
        )
        results.record(
            "native",
            "steps",
            nodes=rt.n_nodes,
            springs=len(rt.springs),
            hexahedra=len(rt.hexahedra),
            threads=threads,
            c_loop_steps_per_s=c_rate,
            native_steps_per_s=native_rate,
            native_cpu_us_per_step=cpu * 1e6,
            python_overhead_us=1e6 / native_rate - 1e6 / c_rate,
            float32_steps_per_s=f32_rate,
            numpy_steps_per_s=numpy_rate,
            speedup_over_numpy=c_rate / numpy_rate,
            step_bytes=nbytes,
            stream_steps_per_s=1.0 / stream,
            stream_ratio=ratio,
            goal_steps_per_s=goal,
            meets_goal=None if goal is None else c_rate >= goal,
            meets_stream_goal=ratio <= STREAM_GOAL,
            meets_numpy_goal=c_rate / numpy_rate >= NUMPY_GOAL,
            load_average=load,
        )


if __name__ == "__main__":
    main()
    results.save("native", "python -m bench.bench_native")
