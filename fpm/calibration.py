"""Calibration: fit the FPM's (k, d, depth) to the FEM reference (paper Sec. 4.2-4.4).

Data flow: :func:`run_chain` (one seeded annealing chain; a worker runs one per job) ->
:func:`finalize` (the best over chains, the fastest-settling among near-best states, the
depth, the discrepancies) -> :class:`CalibrationResult`. :func:`calibrate` does both in-process.

Defaults (see also :class:`fpm.spec.AnnealingSettings`):
- cost is normalised by the reference cost (the cost of an FPM that does not move), so
  temperatures and c_max are scale-free;
- k bounds: [E h / 100, 10 E h] (a lattice of spacing h has an effective modulus of order k/h);
- d bounds: [0.1, 5] sqrt(E h m), m the mean node mass: sqrt(k m) is the damping scale of a
  node on springs of stiffness k ~ E h; below the range the run diverges at any practical time
  step, above it the run creeps and does not settle;
- depth 'auto': fit at full depth, then the smallest depth whose FPM result is within 1% of h
  (mean nodal difference, worst load case) of the full-depth result (physics.md).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .annealing import AnnealingError, Schedule, State, anneal
from .cost import CostFunction
from .problem import Problem

NEAR_BEST = 0.001
"""States within this fraction of the best cost are equally good; the fastest-settling wins."""
SAME_SPEED = 0.05
"""Settle step counts within this fraction of the fewest are equally fast; the cheapest wins."""
AUTO_DEPTH_TOLERANCE = 0.01
"""Depth 'auto': largest allowed mean nodal difference from full depth, as a fraction of h."""

Progress = Callable[[dict[str, Any]], None]


@dataclass
class ChainResult:
    """One annealing chain's outcome (JSON-able through :meth:`to_dict`).

    Attributes:
        chain: chain index (the generator is seeded with (spec seed, chain)).
        k, d: best state, N/m and N s/m.
        cost: its normalised cost (Eq. 2 / reference cost).
        evaluations: cost evaluations (one per move, plus the start).
        accepted: accepted moves.
        history: normalised current cost after each move.
        near_best: states within 1% of this chain's best: dicts k, d, cost, steps, settled.
        seconds: wall time.
    """

    chain: int
    k: float
    d: float
    cost: float
    evaluations: int
    accepted: int
    history: list[float]
    near_best: list[dict[str, Any]]
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ChainResult:
        return cls(**data)


@dataclass
class CalibrationResult:
    """The fitted parameter set and how well it fits.

    Attributes:
        k: spring stiffness, N/m.
        d: nodal damping, N s/m.
        depth: penetration depth, layers.
        cost: Eq. (2) at (k, d, depth), m.
        discrepancy: mean nodal discrepancy per load case, % of h.
        settle_steps: time steps to settle, per load case.
        settled: every load case settled within max_steps.
        evaluations: cost evaluations over all chains.
        seconds: wall time of the annealing (sum over chains run in parallel is not counted).
        history: normalised current cost per move of the winning chain.
        h: shortest spring rest length, m.
        chains: per chain: k, d, cost, evaluations.
    """

    k: float
    d: float
    depth: int
    cost: float
    discrepancy: list[float]
    settle_steps: list[int]
    settled: bool
    evaluations: int
    seconds: float
    history: list[float]
    h: float
    chains: list[dict[str, Any]] = field(default_factory=list)

    @property
    def mean_discrepancy(self) -> float:
        return float(np.mean(self.discrepancy))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def search_bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) for (k, d): the spec's bounds, else the defaults of this module."""
    spec = problem.spec
    eh = spec.material.youngs_modulus * problem.h
    k = spec.annealing.bounds.k or (eh / 100, 10 * eh)
    scale = float(np.sqrt(eh * problem.solid.masses.mean()))
    d = spec.annealing.bounds.d or (0.1 * scale, 5 * scale)
    return np.array([k[0], d[0]]), np.array([k[1], d[1]])


def fit_depth(problem: Problem) -> int | None:
    """The depth chains fit at: the spec's integer, or None (every layer) for 'auto'."""
    depth = problem.spec.fpm.depth
    return None if depth == "auto" else int(depth)


def reference_displacements(reference: Any) -> np.ndarray:
    """(L, N, 3) from a FemResult (``.displacements``) or an array."""
    return np.asarray(getattr(reference, "displacements", reference), dtype=float)


def run_chain(
    problem: Problem,
    reference: Any,
    chain: int,
    *,
    progress: Progress | None = None,
    checkpoint: Progress | None = None,
    resume: dict[str, Any] | None = None,
) -> ChainResult:
    """One annealing chain over (k, d), seeded by (spec seed, ``chain``): exactly repeatable.

    ``progress`` gets {chain, move, moves, temperature, best_cost, current_cost} after each move;
    ``checkpoint`` gets a JSON-able state every few moves, which ``resume`` continues from.
    """
    t0 = time.perf_counter()
    a = problem.spec.annealing
    cost = CostFunction(problem, reference_displacements(reference), fit_depth(problem))
    if cost.reference_cost <= 0:
        raise AnnealingError("the reference does not move: nothing to fit")

    # An unsettled FPM is still moving: its cost measures a transient, not the model, and its
    # parameters are no use in a real-time loop. Such a candidate is rejected like a divergent
    # one, unless the spec asks never to settle (settle_tolerance 0).
    settling = problem.spec.fpm.settle_tolerance > 0

    def objective(x: list[float]) -> State:
        ev = cost(x[0], x[1], stop_unsettled=settling)
        info = {"steps": ev.steps, "settled": ev.settled}
        return State(list(x), ev.cost / cost.reference_cost, info)

    def report(info: dict[str, Any]) -> None:
        if progress is not None:
            progress({"chain": chain, **info})

    lower, upper = search_bounds(problem)
    result = anneal(
        objective,
        lower,
        upper,
        Schedule(a.t_initial, a.t_final, a.beta),
        np.random.default_rng([a.seed, chain]),
        c_max=a.c_max,
        progress=report,
        checkpoint=checkpoint,
        resume=resume,
    )
    near = [
        {
            "k": s.x[0],
            "d": s.x[1],
            "cost": s.cost,
            "steps": s.info["steps"],
            "settled": s.info["settled"],
        }
        for s in result.visited
    ]
    return ChainResult(
        chain=chain,
        k=result.best.x[0],
        d=result.best.x[1],
        cost=result.best.cost,
        evaluations=result.evaluations,
        accepted=result.accepted,
        history=result.history,
        near_best=near,
        seconds=time.perf_counter() - t0,
    )


def finalize(problem: Problem, reference: Any, chains: list[ChainResult]) -> CalibrationResult:
    """The calibration result from the chains' outcomes.

    Among all states within 0.1% of the best cost over every chain, the one that settles in the
    fewest total steps wins (physics.md); step counts within 5% of the fewest count as equally
    fast, and among those the cheapest wins (a few steps more or less mean nothing to a
    real-time loop, while the cost still tells k apart). Then the depth is resolved and the
    discrepancies are measured at (k, d, depth).
    """
    if not chains:
        raise ValueError("no chain results")
    best_cost = min(c.cost for c in chains)
    candidates = [
        s for c in chains for s in c.near_best if s["cost"] <= best_cost * (1 + NEAR_BEST)
    ]
    if any(s["settled"] for s in candidates):
        candidates = [s for s in candidates if s["settled"]]
    fewest = min(sum(s["steps"]) for s in candidates)
    fast = [s for s in candidates if sum(s["steps"]) <= fewest * (1 + SAME_SPEED)]
    pick = min(fast, key=lambda s: (s["cost"], sum(s["steps"])))
    k, d = pick["k"], pick["d"]
    disp = reference_displacements(reference)
    depth = fit_depth(problem)
    cost = CostFunction(problem, disp, depth)
    if depth is None:
        depth = auto_depth(cost, k, d)
        cost.depth = depth
    final = cost(k, d)
    winner = min(chains, key=lambda c: c.cost)
    return CalibrationResult(
        k=k,
        d=d,
        depth=depth,
        cost=final.cost,
        discrepancy=cost.discrepancy(k, d),
        settle_steps=final.steps,
        settled=final.settled,
        evaluations=sum(c.evaluations for c in chains),
        seconds=max(c.seconds for c in chains),
        history=winner.history,
        h=problem.h,
        chains=[
            {"chain": c.chain, "k": c.k, "d": c.d, "cost": c.cost, "evaluations": c.evaluations}
            for c in chains
        ],
    )


def auto_depth(cost: CostFunction, k: float, d: float) -> int:
    """Smallest depth whose result is within 1% of h of the full-depth result, every load case."""
    full = [cost.displacements(k, d, j, None) for j in range(len(cost.problem.load_cases))]
    deepest = max(r.depth for r in full)
    for depth in range(0, deepest + 1):
        worst = max(
            np.linalg.norm(
                cost.displacements(k, d, j, depth).displacements - r.displacements, axis=1
            ).mean()
            for j, r in enumerate(full)
        )
        if worst <= AUTO_DEPTH_TOLERANCE * cost.problem.h:
            return depth
    return deepest


def calibrate(
    problem: Problem,
    *,
    chains: int | None = None,
    progress: Progress | None = None,
    reference: Any = None,
    threads: int | None = None,
) -> CalibrationResult:
    """Fit (k, d, depth) for ``problem`` in-process.

    Args:
        problem: from :func:`fpm.load_problem`.
        chains: number of annealing chains (None = the spec's).
        progress: called with {phase, chain, move, moves, temperature, best_cost, ...}.
        reference: FEM result or (L, N, 3) displacements (None = solve the FEM now).
        threads: chains run at once (None = one per core); the step releases the GIL.
    """
    n = problem.spec.annealing.chains if chains is None else chains
    if n < 1:
        raise ValueError("chains must be >= 1")
    if reference is None:
        from .fem import solve_fem

        if progress is not None:
            progress({"phase": "fem"})
        reference = solve_fem(problem)

    def one(chain: int) -> ChainResult:
        cb = None if progress is None else (lambda info: progress({"phase": "annealing", **info}))
        return run_chain(problem, reference, chain, progress=cb)

    workers = min(n, threads or os.cpu_count() or 1)
    if workers == 1:
        results = [one(c) for c in range(n)]
    else:
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(one, range(n)))
    if progress is not None:
        progress({"phase": "finalize"})
    return finalize(problem, reference, results)
