"""``fpm.step_budget_us``: the deepest perturbed list whose step fits a frame budget here.

The paper's penetration depth is its speed control (Sec. 3.1, Fig. 7: a step costs what the
list holds): a haptic loop with 1 ms a frame, a step's share of it given, wants the most
faithful model that meets it. The model is the fitted one; what changes is how far its list
reaches. So the budget caps the depth the calibration resolved (depth 'auto' or the spec's):
the answer is the deepest depth, at most that one, whose region step
(:meth:`fpm.runtime.Runtime.region`, the list free and the ring beyond it at rest) takes at
most the budget in every load case, fitted and validation, on the machine that calibrates,
with the runtime's fastest backend. A deeper list moves more of the solid, so within the
budget it is the faithful one; the result's figures are at that depth, and it names the
machine, the backend and the microseconds measured.

Timing is the wall clock of a loop of steps under the case's forces, the best of three
(a shared machine only ever slows a loop down), after a few steps to warm the caches.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..dynamics.stability import auto_time_step
from ..model.forces import Stiffness, cells
from ..model.problem import Problem
from ..runtime import Runtime

TIMED_STEPS = 50
"""Steps per timed loop (a region of 10^4 nodes steps them in a few ms)."""


def cpu_name() -> str:
    """The processor's name as the system gives it (``/proc/cpuinfo``'s model name where
    there is one): with the core count, the machine a timing holds for."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return cpu


def runtime_of(
    problem: Problem,
    stiffness: Stiffness,
    d: float,
    dt: float | None = None,
    backend: str = "auto",
    precision: str = "float64",
) -> Runtime:
    """The runtime of the lattice at ``stiffness`` with damping ``d`` (N s/m) and ``dt`` (s;
    None: :func:`fpm.dynamics.stability.auto_time_step`), stepped by ``backend`` in
    ``precision``: the JSON export's arrays (the volume term's where the model has one), built
    from the problem without an export, settling never (a timing loop's)."""
    hexahedra = problem.solid.elements() if stiffness.volume is not None else None
    volume = hexahedra is not None
    return Runtime(
        rest=problem.nodes,
        masses=problem.solid.masses,
        fixed=problem.fixed,
        springs=problem.solid.springs.astype(np.int64),
        rest_lengths=problem.rest_lengths,
        stiffness=stiffness.springs,
        hexahedra=np.zeros((0, 8), np.int64) if hexahedra is None else hexahedra,
        kappa=np.asarray(stiffness.volume, dtype=float) if volume else np.zeros(0),
        rest_volumes=cells(problem).volume if volume else np.zeros(0),
        d=d,
        dt=auto_time_step(problem, stiffness) if dt is None else dt,
        settle_tolerance=0.0,
        backend=backend,
        precision=precision,
    )


def step_microseconds(runtime: Runtime, forces: np.ndarray) -> float:
    """Wall microseconds a step of ``runtime`` takes under ``forces`` (N, 3), N: the best of
    three loops of :data:`TIMED_STEPS` steps, after ten to warm up."""
    f = np.ascontiguousarray(forces, dtype=runtime.x.dtype)
    for _ in range(10):
        runtime.step(f)
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(TIMED_STEPS):
            runtime.step(f)
        best = min(best, (time.perf_counter() - start) / TIMED_STEPS)
    runtime.reset()
    return 1e6 * best


def budget_depth(
    problem: Problem, stiffness: Stiffness, dt: float | None, budget_us: float, deepest: int
) -> dict[str, Any]:
    """The deepest depth in 1..``deepest`` whose region step meets ``budget_us`` (µs) in every
    load case of ``problem`` (fitted and validation) at ``stiffness`` and ``dt`` (s; None:
    auto); the step
    cost grows with depth, so it is found by bisection.

    Returns the result's ``step_budget``: ``budget_us``, ``depth`` (1 when even one layer is
    over the budget: then ``met`` is False), ``met``, ``microseconds`` (per load case at that
    depth), ``nodes`` (the largest region's), ``probed`` ({depth: the slowest case's µs}),
    ``backend`` and ``machine``.
    """
    whole = runtime_of(problem, stiffness, 1.0, dt)
    cases = [(c.nodes, c.dense(problem.n_nodes)) for c in problem.all_cases]
    probed: dict[int, tuple[list[float], int]] = {}

    def timed(depth: int) -> float:
        if depth not in probed:
            times, nodes = [], 0
            for loaded, forces in cases:
                region = whole.region(loaded, depth)
                times.append(step_microseconds(region.runtime, region.forces(forces)))
                nodes = max(nodes, len(region.nodes))
            probed[depth] = (times, nodes)
        return max(probed[depth][0])

    low, high = 1, max(1, deepest)
    if timed(high) <= budget_us:
        low = high
    elif timed(low) <= budget_us:  # low meets it, high does not
        while high - low > 1:
            mid = (low + high) // 2
            low, high = (mid, high) if timed(mid) <= budget_us else (low, mid)
    times, nodes = probed[low]
    return {
        "budget_us": float(budget_us),
        "depth": low,
        "met": max(times) <= budget_us,
        "microseconds": times,
        "nodes": nodes,
        "probed": {str(k): max(v[0]) for k, v in sorted(probed.items())},
        "backend": whole.backend_used,
        "machine": f"{cpu_name()}, {os.cpu_count()} cores",
    }


def budget_notes(budget: dict[str, Any] | None) -> list[str]:
    """The warning of a budget not met (:func:`budget_depth`'s answer; None: no budget)."""
    if budget is None or budget["met"]:
        return []
    return [
        f"fpm.step_budget_us: even one layer takes {max(budget['microseconds']):,.0f} µs a step "
        f"on {budget['machine']} ({budget['backend']}), over the {budget['budget_us']:,.0f} µs "
        "asked: the result is at depth 1; a coarser lattice (fewer nodes) or a larger budget "
        "meets it"
    ]
