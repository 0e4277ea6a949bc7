"""Stage 2 of the calibration: the nodal damping d that settles fastest (docs/physics.md).

A settled FPM state does not depend on d; d only decides how fast, and whether, a run settles
at the spec's dt. So once the stiffness is fitted, d is chosen for the real-time loop: the value
in the search bounds that settles every load case in the fewest total time steps, found with the
real dynamic kernel (:class:`fpm.simulation.FpmModel`).

First guess (:func:`critical_damping`): the slowest motion a load excites is close to the
static deflection u = K^-1 f, so Rayleigh's quotient of that shape, omega^2 = f.u / (u^T M u),
estimates its frequency, and critical damping of a mode with nodal damping d I and lumped masses
M is d = 2 omega (u^T M u) / (u^T u). The search (:func:`fastest_damping`) brackets the fewest
total steps around the guess on a log scale (steps from 1.25x, growing), refines it by a few
parabolic steps through the best d and its neighbours (or halves the gap towards a neighbour
that did not settle), and then looks for the smallest d that still settles every load case
within MARGIN_CAP times its fastest steps, walking down from the smallest settling d (the
stability margin: the fastest d sits near that edge, and below it runs diverge or creep). The
runs of the fastest d are kept: they are the calibration's final dynamic check.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .problem import Problem
from .simulation import FpmModel

BRACKET_STEP = 1.25
"""The bracket walks from the guess by this factor (the Rayleigh guess is usually close)."""
WALK_GROWTH = 1.6
"""Each further bracket step is this much longer (on log d) than the last."""
RESOLUTION = 1.02
"""Parabolic steps stop once a new d is within this factor of one already tried."""
REFINE_STEPS = 4
"""At most this many refining runs after the bracket."""
MARGIN_CAP = 3
"""A d 'still settles' for the margin if every load case settles within this many times its
steps at the fastest d (below the margin a run diverges or creeps; capping keeps the margin
search as cheap as the rest)."""


@dataclass
class DampingFit:
    """The fastest-settling d for a fitted stiffness.

    Attributes:
        d: nodal damping, N s/m.
        steps: (L,) time steps each load case takes to settle at d.
        displacements: (L, N, 3) the settled displacements at d, m.
        d_min: smallest d found that settles every load case within MARGIN_CAP times its
            steps at d, N s/m (to a factor of about 1.12; the lower bound if that settles).
        guess: the critical-damping estimate the search started from, N s/m.
        runs: dynamic runs made (one per load case per d tried).
        tried: (d, total steps or None when some load case did not settle) for every d tried.
    """

    d: float
    steps: list[int]
    displacements: np.ndarray
    d_min: float
    guess: float
    runs: int
    tried: list[tuple[float, int | None]] = field(default_factory=list)

    @property
    def total_steps(self) -> int:
        return int(sum(self.steps))


def critical_damping(problem: Problem, displacements: np.ndarray) -> float:
    """Critical damping estimate, N s/m, from static displacements (L, N, 3) (Rayleigh).

    The geometric mean over load cases of ``2 omega (u^T M u) / (u^T u)`` with
    ``omega^2 = f.u / (u^T M u)``.
    """
    m = problem.solid.masses
    estimates = []
    for j, case in enumerate(problem.load_cases):
        u = displacements[j]
        f = case.dense(problem.n_nodes)
        mu2 = float(np.einsum("n,ni,ni->", m, u, u))
        u2 = float(np.einsum("ni,ni->", u, u))
        work = float(np.einsum("ni,ni->", f, u))
        if mu2 > 0 and work > 0:
            estimates.append(2 * math.sqrt(work / mu2) * mu2 / u2)
    if not estimates:
        raise ValueError("no load case moves: cannot estimate the damping")
    return float(np.exp(np.mean(np.log(estimates))))


class _Runs:
    """Runs every load case at one d (in threads: the kernel releases the GIL)."""

    def __init__(self, problem: Problem, stiffness: np.ndarray, depth: int | None):
        self.problem = problem
        self.stiffness = stiffness
        self.depth = depth
        cases = len(problem.load_cases)
        self.models = [FpmModel(problem) for _ in range(cases)]
        self.threads = min(cases, os.cpu_count() or 1)
        self.count = 0

    def __call__(self, d: float, max_steps: int) -> list[Any]:
        s = self.problem.spec.fpm

        def one(j: int) -> Any:
            return self.models[j].run(
                j, k=self.stiffness, d=d, depth=self.depth, dt=s.dt,
                max_steps=max_steps, settle_tolerance=s.settle_tolerance,
            )  # fmt: skip

        self.count += len(self.models)
        if self.threads == 1:
            return [one(j) for j in range(len(self.models))]
        with ThreadPoolExecutor(self.threads) as pool:
            return list(pool.map(one, range(len(self.models))))


def fastest_damping(
    problem: Problem,
    stiffness: np.ndarray,
    depth: int | None,
    bounds: tuple[float, float],
    guess: float,
    *,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> DampingFit:
    """The d in ``bounds`` that settles every load case in the fewest total steps.

    Args:
        problem: the problem (dt, max_steps, settle_tolerance from its spec).
        stiffness: (S,) per-spring stiffness, N/m (:func:`fpm.stiffness.spring_stiffness`).
        depth: penetration depth (None = every layer).
        bounds: (low, high) for d, N s/m.
        guess: where to start (e.g. :func:`critical_damping`), clipped into the bounds.
        progress: called with {"d", "total_steps"} after each d tried.

    Raises:
        DampingError: no d in the bounds settles every load case within max_steps.
    """
    lo, hi = round(math.log(bounds[0]), 12), round(math.log(bounds[1]), 12)
    max_steps = problem.spec.fpm.max_steps
    runs = _Runs(problem, stiffness, depth)
    steps: dict[float, list[int] | None] = {}  # log d -> steps per case (None: not settled)
    best: list[Any] = []  # [log d, displacements (L, N, 3)] of the fewest total steps so far

    def total(y: float) -> float:
        """Total steps at d = exp(y); inf if some case did not settle within the cap."""
        y = round(min(max(y, lo), hi), 12)  # one key per d, whatever path computed it
        if y not in steps:
            # No need to run past the best total so far: such a d cannot win.
            cap = min(max_steps, _total(steps[best[0]]) + 1) if best else max_steps
            results = runs(math.exp(y), cap)
            ok = all(r.settled for r in results)
            steps[y] = [int(r.steps) for r in results] if ok else None
            if ok and (not best or _total(steps[y]) < _total(steps[best[0]])):
                best[:] = [y, np.stack([r.displacements for r in results])]
            if progress is not None:
                found = steps[y]
                progress({"d": math.exp(y), "total_steps": None if found is None else sum(found)})
        return float(_total(steps[y])) if steps[y] is not None else math.inf

    # Bracket: walk from the guess towards fewer steps, each step 1.6x longer (the guess can
    # be a few times off: a soft organ's lowest modes are slower than its static deflection).
    y0 = min(max(math.log(guess), lo), hi)
    step = math.log(BRACKET_STEP)
    left, mid, right = max(y0 - step, lo), y0, min(y0 + step, hi)
    f_left, f_mid, f_right = total(left), total(mid), total(right)
    walk = step
    while f_left < f_mid and left > lo:
        walk *= WALK_GROWTH
        right, f_right, mid, f_mid = mid, f_mid, left, f_left
        left = max(mid - walk, lo)
        f_left = total(left)
    while f_right < f_mid and right < hi:
        walk *= WALK_GROWTH
        left, f_left, mid, f_mid = mid, f_mid, right, f_right
        right = min(mid + walk, hi)
        f_right = total(right)
    if not best:  # nothing settled around the guess: scan the whole range
        for y in np.linspace(lo, hi, 9):
            total(float(y))
        if not best:
            raise DampingError(
                f"no d in [{bounds[0]:.3g}, {bounds[1]:.3g}] N s/m settles every load case "
                f"within max_steps={max_steps}: raise max_steps, lower dt (see the lattice's "
                "stability estimate, fpm.diagnosis.stable_time_step) or widen annealing.bounds.d"
            )
    # Refine: a parabolic step through the best d and its neighbours, or, where a neighbour
    # did not settle, halve the gap towards it.
    for _ in range(REFINE_STEPS):
        y = _next_point(steps, best[0])
        if y is None:
            break
        total(y)
    y_best, displacements = best
    return DampingFit(
        d=math.exp(y_best),
        steps=list(steps[y_best] or []),
        displacements=displacements,
        d_min=math.exp(_smallest_settling(runs, steps, y_best, lo, max_steps, step)),
        guess=math.exp(y0),
        runs=runs.count,
        tried=sorted((math.exp(y), None if s is None else sum(s)) for y, s in steps.items()),
    )


def _total(steps: list[int] | None) -> int:
    return sum(steps) if steps is not None else 1 << 62


def _next_point(steps: dict[float, list[int] | None], y_best: float) -> float | None:
    """Where to look next (log d), or None once the best is resolved to RESOLUTION.

    With a tried d on each side of the best: the vertex of the parabola through the three when
    both settled, else the middle of the gap to the side that did not settle (the wider such
    gap first). A point closer than RESOLUTION to a tried d is not worth a run."""
    tried = sorted(steps)
    i = tried.index(y_best)
    left = tried[i - 1] if i > 0 else None
    right = tried[i + 1] if i + 1 < len(tried) else None
    resolution = math.log(RESOLUTION)
    candidates = []
    if left is not None and right is not None and steps[left] and steps[right]:
        (a, b, c) = (left, y_best, right)
        fa, fb, fc = _total(steps[a]), _total(steps[b]), _total(steps[c])
        denominator = (b - a) * (fb - fc) - (b - c) * (fb - fa)
        if denominator != 0:
            vertex = b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)) / denominator
            candidates.append(min(max(vertex, a), c))
    gaps = [(abs(y_best - n), n) for n in (left, right) if n is not None and not steps[n]]
    candidates += [(y_best + n) / 2 for _, n in sorted(gaps, reverse=True)]
    for y in candidates:
        if min(abs(y - t) for t in tried) >= resolution:
            return y
    return None


def _smallest_settling(
    runs: _Runs,
    steps: dict[float, list[int] | None],
    y_best: float,
    lo: float,
    max_steps: int,
    step: float,
) -> float:
    """log d of the smallest d whose runs all settle within MARGIN_CAP times their steps at the
    fastest d: from the smallest settling d tried, down by ``step`` (log) while it settles, then
    one bisection (the fastest d sits near the edge, so this takes few runs)."""
    fastest = steps[y_best] or []
    caps = [min(max_steps, MARGIN_CAP * s) for s in fastest]

    def settles(y: float) -> bool:
        if steps.get(y) is not None:
            return all(s <= c for s, c in zip(steps[y] or [], caps, strict=True))
        results = runs(math.exp(y), max(caps))
        return all(r.settled and r.steps <= c for r, c in zip(results, caps, strict=True))

    y_ok = min(y for y, s in steps.items() if s is not None and settles(y))
    while y_ok > lo:
        y = max(y_ok - step, lo)
        if not settles(y):
            middle = (y + y_ok) / 2
            return middle if settles(middle) else y_ok
        y_ok = y
    return y_ok


class DampingError(RuntimeError):
    """No d in the bounds settles every load case."""
