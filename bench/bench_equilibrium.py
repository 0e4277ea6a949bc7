"""Static equilibrium speed (:mod:`fpm.dynamics.equilibrium`) on the voxelised organ
(bench/organ.py).

The use it is built for: a simulated-annealing calibration calls the static solve ~300 times
per load case with nearby stiffnesses (one k, or one k per spring family), so what matters is
the warm solve. Per mesh spacing h, with k0 = 0.35 E h and full depth:

- cold: a fresh solver, each load case from rest (the first also builds the multigrid
  hierarchy that the rest reuse);
- warm, one earlier solution: the solver remembers only the solution at k0 (hierarchy kept),
  then solves at k0 * factor (single k) or at family stiffnesses changed by (+5, -5, +5)%;
- annealing-like: a seeded random walk (log-normal 5% moves, half accepted) over the three
  load cases, as the annealer calls it; the solver remembers its last solutions
  (:class:`fpm.dynamics.predictor._Predictor`). Mean and median per solve after the first 10
  moves, and the projected time of 300 moves x 3 load cases; with families also at a relative
  tolerance of 1e-4 instead of the default 1e-6 (settle_tolerance / 10).

Run: python -m bench equilibrium (or python -m bench.bench_equilibrium [h ...]).
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

import fpm
from bench.organ import ellipsoid_spec
from fpm.dynamics.equilibrium import StaticSolver
from fpm.model.stiffness import spring_stiffness

SPACINGS = (0.005, 0.003)
"""Mesh spacings h, m: 4,612 and 19,692 nodes."""
FAMILY_RATIOS = (1.0, 0.7, 0.5)
"""Family stiffnesses (axis, face, body diagonal) as multiples of k0."""
MOVES = 50
"""Moves of the annealing-like walk."""
SETTLED_FROM = 10
"""Moves after which the walk's statistics are taken (the solver has earlier solutions)."""


def row(label: str, result: Any, seconds: float) -> str:
    return (
        f"{label:<34} {result.perturbed * 3:>8} {seconds:>8.3f} {result.iterations:>6} "
        f"{result.linear_iterations:>6} {'yes' if result.converged else 'NO':>5}"
    )


def bench_spacing(h: float, families: bool) -> None:
    spec = ellipsoid_spec(h)
    if families:
        spec["fpm"] = {"stiffness": "families"}
    problem = fpm.load_problem(spec)
    k0 = 0.35 * problem.spec.material.youngs_modulus * h
    theta0 = k0 * np.array(FAMILY_RATIOS if families else (1.0,))
    cases = range(len(problem.load_cases))
    kind = "families" if families else "single k"
    print(f"\nh = {h * 1e3:g} mm, {problem.n_nodes} nodes, {kind}, k0 = {k0:.3g} N/m")
    print(f"{'solve':<34} {'unknowns':>8} {'seconds':>8} {'Newton':>6} {'CG':>6} {'conv':>5}")

    solver = StaticSolver(problem)
    stiffness0 = spring_stiffness(problem, theta0)
    for case in cases:
        t0 = time.perf_counter()
        result = solver.solve(case, stiffness0, None)
        print(row(f"cold, load case {case}", result, time.perf_counter() - t0))

    if families:
        changes = [("families +5/-5/+5%", np.array([1.05, 0.95, 1.05]))]
    else:
        changes = [(f"k {f - 1:+.0%}", np.array([f])) for f in (1.01, 1.05, 1.3)]
    for label, factor in changes:
        for case in cases:
            solver._predictors.clear()  # the next solves start from rest
            solver.solve(case, stiffness0, None)
            t0 = time.perf_counter()
            result = solver.solve(case, spring_stiffness(problem, theta0 * factor), None)
            print(row(f"warm after {label}, case {case}", result, time.perf_counter() - t0))

    for tolerance in (None, 1e-4) if families else (None,):
        walk(problem, solver, theta0, tolerance)


def walk(
    problem: fpm.Problem, solver: StaticSolver, theta0: np.ndarray, tolerance: float | None
) -> None:
    """The annealing-like random walk; prints one summary line."""
    solver._predictors.clear()  # the next solves start from rest
    built = solver.hierarchies_built
    rng = np.random.default_rng(0)
    theta = theta0.copy()
    times: list[float] = []
    newton: list[int] = []
    cases = range(len(problem.load_cases))
    for move in range(MOVES):
        candidate = theta * np.exp(rng.normal(0.0, 0.05, len(theta)))
        stiffness = spring_stiffness(problem, candidate)
        for case in cases:
            t0 = time.perf_counter()
            result = solver.solve(case, stiffness, None, tolerance=tolerance)
            if move >= SETTLED_FROM:
                times.append(time.perf_counter() - t0)
                newton.append(result.iterations)
            assert result.converged, result.message
        if rng.random() < 0.5:
            theta = candidate
    mean, median = float(np.mean(times)), float(np.median(times))
    print(
        f"annealing-like walk, tolerance {result.tolerance:g}: mean {mean:.3f} s, median "
        f"{median:.3f} s, max {max(times):.3f} s per solve, {np.mean(newton):.2f} Newton "
        f"iterations, {solver.hierarchies_built - built} hierarchies rebuilt; "
        f"300 moves x {len(cases)} cases ~ {300 * len(cases) * mean:.0f} s"
    )


def main(spacings: tuple[float, ...] = SPACINGS) -> None:
    for h in spacings:
        for families in (False, True):
            bench_spacing(h, families)


if __name__ == "__main__":
    main(tuple(float(a) for a in sys.argv[1:]) or SPACINGS)
