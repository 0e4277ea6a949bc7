"""Choosing d two ways at one fitted stiffness: the damping stage's choice (the spectral
prediction from the slowest modes, then the lockstep search:
:func:`fpm.fitting.damping.choice.fit_damping`) against a plain golden-section search over
log d in :func:`fpm.fitting.bounds.damping_bounds` that simulates every trial d's load cases to
settle (the same settle criterion, cap, stiffness, depth and dt as the stage's runs).

On the paper's cube (material A, ``examples/paper-material-a.json``), calibrated in-process
first (FEM outside the timing) for its stiffness, depth and dt. Printed per method: settle
runs (one per load case per d), total kernel steps, wall time (s), the chosen d (N s/m) and
its steps to settle per load case; the load average beside it (a shared machine). Rows go to
bench/results/stage2.json.

Run: python -m bench stage2.
"""

from __future__ import annotations

import json
import math
import os
import time
from typing import Any

import numpy as np

from bench import results
from bench.bench_calibration import SPEC_A

GOLDEN_TRIALS = 14
"""Trial d of the plain search: 2 to open the bracket, then golden-section steps on log d."""


def _fitted(spec: dict[str, Any]) -> tuple[Any, Any, Any]:
    """(problem, calibration result, FEM reference) of an in-process two-stage calibration."""
    import fpm
    from fpm.fitting.calibration import calibrate

    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    return problem, calibrate(problem, reference=reference), reference


def _setting(
    problem: Any, result: Any, reference: Any
) -> tuple[Any, Any, int, np.ndarray, np.ndarray]:
    """The stage's inputs at the result: (solver, stiffness, depth, static (L, N, 3) m, the
    reference's displacements (L, N, 3) m, which the settle distances 'auto' read)."""
    from fpm.dynamics.equilibrium import StaticSolver
    from fpm.fitting.reference import reference_displacements
    from fpm.model.stiffness import fitted_theta, model_stiffness

    stiffness = model_stiffness(problem, fitted_theta(problem, result.to_dict()))
    solver = StaticSolver(problem)
    depth = int(result.parameters.depth)
    static = np.stack(
        [solver.solve(j, stiffness, depth).displacements for j in range(len(problem.load_cases))]
    )
    return solver, stiffness, depth, static, reference_displacements(reference, problem)


def stage_choice(problem: Any, result: Any, fem: Any) -> dict[str, Any]:
    """The stage's own choice of d, timed from the prediction on."""
    from fpm.fitting.damping.choice import fit_damping

    solver, stiffness, depth, static, reference = _setting(problem, result, fem)
    t0 = time.perf_counter()
    fit, plan = fit_damping(
        problem, solver, stiffness, depth, static, result.settle.dt, reference=reference
    )
    wall = time.perf_counter() - t0
    return {
        "method": "prediction + lockstep",
        "runs": fit.runs,
        "kernel_steps": fit.work,
        "wall_s": wall,
        "d": fit.d,
        "steps": list(fit.steps),
        "_plan": plan,
        "_cap": fit.max_steps,
        "_static": static,
        "_stiffness": stiffness,
        "_depth": depth,
    }


def golden_choice(problem: Any, result: Any, stage: dict[str, Any]) -> dict[str, Any]:
    """A plain golden-section search on log d over the bounds, every trial d's cases run to
    settle (or the stage's cap) on the stage's settle criterion."""
    from fpm.dynamics.settle import run_criterion
    from fpm.dynamics.simulation import FpmModel
    from fpm.fitting.bounds import damping_bounds

    plan, cap, static = stage["_plan"], stage["_cap"], stage["_static"]
    model = FpmModel(problem)
    cases = len(problem.load_cases)
    settle = [
        run_criterion(
            problem.spec,
            None if plan.settle is None else plan.settle[j],
            None if plan.distance is None else static[j],
            None if plan.distance is None else plan.distance[j],
        )
        for j in range(cases)
    ]
    seen: dict[float, list[int] | None] = {}
    counts = {"runs": 0, "steps": 0}

    def total(y: float) -> float:
        if y not in seen:
            steps: list[int] | None = []
            for j in range(cases):
                run = model.run(
                    j, k=stage["_stiffness"], d=math.exp(y), depth=stage["_depth"],
                    dt=result.settle.dt, max_steps=cap, settle=settle[j],
                )  # fmt: skip
                counts["runs"] += 1
                counts["steps"] += run.steps
                if not run.settled:
                    steps = None
                    break
                steps.append(run.steps)  # type: ignore[union-attr]
            seen[y] = steps
        found = seen[y]
        return math.inf if found is None else float(sum(found))

    t0 = time.perf_counter()
    lo, hi = (math.log(b) for b in damping_bounds(problem))
    ratio = (math.sqrt(5) - 1) / 2
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = total(a), total(b)
    for _ in range(GOLDEN_TRIALS - 2):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = total(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = total(b)
    wall = time.perf_counter() - t0
    best = min((y for y in seen if seen[y] is not None), key=total, default=None)
    return {
        "method": "golden section",
        "runs": counts["runs"],
        "kernel_steps": counts["steps"],
        "wall_s": wall,
        "d": None if best is None else math.exp(best),
        "steps": [] if best is None else list(seen[best] or []),
    }


def main() -> None:
    spec = json.loads(SPEC_A.read_text())
    problem, result, fem = _fitted(spec)
    stage = stage_choice(problem, result, fem)
    golden = golden_choice(problem, result, stage)
    load = os.getloadavg()
    print(f"\nChoosing d on the cube (material A), load average {load[0]:.2f} {load[1]:.2f}")
    print(f"   {'method':<24}{'runs':>6}{'kernel steps':>14}{'wall s':>9}{'d':>10}  steps")
    for row in (stage, golden):
        d = f"{row['d']:.4g}" if row["d"] else "-"
        print(
            f"   {row['method']:<24}{row['runs']:>6d}{row['kernel_steps']:>14,d}"
            f"{row['wall_s']:>9.2f}{d:>10}  {row['steps']}"
        )
        fields = {k: v for k, v in row.items() if not k.startswith("_")}
        results.record("stage2", "cube", load_average=list(load), **fields)


if __name__ == "__main__":
    main()
