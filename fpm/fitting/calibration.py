"""Calibration: fit the FPM's stiffness, d and depth to the FEM reference (paper Sec. 4.2-4.4).

Two methods (``annealing.method``; docs/physics.md):

- ``two-stage`` (the default). Stage 1: simulated annealing over the stiffness parameters only
  (k, or one k per spring family), each candidate's cost Eq. (2) taken at its static
  equilibrium (:class:`fpm.fitting.cost.StaticCost`; the settled state does not depend on d); then a
  bounded local polish from the best state (:func:`polish`). Stage 2: d, the value that settles
  every load case in the fewest total steps at the spec's dt (:mod:`fpm.fitting.damping`).
- ``paper``: simulated annealing over (stiffness, d) jointly, every candidate run dynamically
  to rest (:class:`fpm.fitting.cost.CostFunction`); among the states within 0.1% of the best
  cost the fastest-settling wins.

Either way, depth 'auto' is resolved on static equilibria (:func:`resolve_depth`) and a last
dynamic run at (stiffness, d, depth) gives the reported cost, discrepancies and settle steps.

Data flow (the service runs each step as a job): :func:`run_chain` (one seeded chain) ->
:func:`fit_damping` (two-stage: polish, depth, d) -> :func:`finalize` -> :class:`CalibrationResult`.
:func:`calibrate` does all of it in-process.

Defaults:
- cost is normalised by the reference cost (the cost of an FPM that does not move), so
  temperatures and c_max are scale-free;
- k bounds (each family): [E h / 100, 10 E h] (a lattice of spacing h has an effective modulus
  of order k/h);
- d bounds: [0.1, 5] sqrt(E h m), m the mean node mass: sqrt(k m) is the damping scale of a
  node on springs of stiffness k ~ E h.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from ..dynamics.equilibrium import StaticSolver
from ..dynamics.simulation import fpm_model
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.problem import Problem
from ..model.stiffness import family_names, spring_stiffness, stiffness_dict
from .annealing import AnnealingError, Checkpoint, Schedule, State, anneal
from .cost import CostFunction, Evaluation, StaticCost, discrepancies
from .damping import critical_damping, fastest_damping
from .result import CalibrationResult, ChainSummary

EQUALLY_GOOD = 0.001
"""Paper method: states within this fraction of the best cost are equally good; the
fastest-settling wins."""
SAME_SPEED = 0.05
"""Paper method: settle step counts within this fraction of the fewest are equally fast."""
STATIC_AGREEMENT = 1e-3
"""The last dynamic run must reproduce the static cost to this fraction, else a warning ..."""
SETTLE_RESOLUTION = 1e-4
"""... or to this fraction of the reference cost, for a fit so close (cost near 0) that the
settle tolerance's own error dominates."""
POLISH_SPAN = 0.1
"""The polish searches log(k) within +-this of the annealed state (inside the bounds)."""
UNIFORM_SPAN = 1.5
"""Families: the single-k start is searched within +-this of the chains' mean log k, and the
family polish may move each log k this far (family stiffnesses can differ several-fold)."""
POLISH_TOLERANCE = 1e-4
"""The polish resolves log(k) to about this (0.01% in k)."""
CEILING_PENALTY = 10.0
"""Weight of a load case's excess over its ceiling in a families polish
(:func:`constrained_cost`)."""

Progress = Callable[[dict[str, Any]], None]


@dataclass
class NearBest:
    """A state a chain visited within 1% of its best cost (the paper method picks among them).

    Attributes:
        x: the parameters; stiffness in N/m, d in N s/m.
        cost: their normalised cost.
        steps: time steps to settle per load case (paper method; None for the two-stage
            method's static evaluations).
        settled: every load case settled.
    """

    x: list[float]
    cost: float
    steps: list[int] | None = None
    settled: bool = True


@dataclass
class ChainResult:
    """One annealing chain's outcome (JSON-able through :meth:`to_dict`).

    Attributes:
        chain: chain index (the generator is seeded with (spec seed, chain)).
        method: "two-stage" (x = stiffness parameters) or "paper" (x = stiffness + [d]).
        x: best state; stiffness in N/m, d in N s/m.
        cost: its normalised cost (Eq. 2 / reference cost).
        evaluations: cost evaluations (one per move, plus the start search's).
        accepted: accepted moves.
        history: normalised current cost after each move.
        near_best: states within 1% of this chain's best (:class:`NearBest`).
        seconds: wall time.
    """

    chain: int
    method: str
    x: list[float]
    cost: float
    evaluations: int
    accepted: int
    history: list[float]
    near_best: list[NearBest]
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ChainResult:
        return cls(**{**data, "near_best": [NearBest(**s) for s in data["near_best"]]})


@dataclass
class FinalRun:
    """The last dynamic run at (stiffness, d, depth) against the reference and the statics.

    Attributes:
        cost: Eq. (2) of the dynamic run, m; static_cost: of the static equilibria, m.
        settle_steps: (L,) steps to settle; settled: every load case settled.
        relative, loaded, h_percent: the discrepancies (:class:`fpm.fitting.cost.Discrepancies`).
        notes: warnings (did not settle; dynamic and static costs disagree).
    """

    cost: float
    static_cost: float
    settle_steps: list[int]
    settled: bool
    relative: list[float]
    loaded: list[float]
    h_percent: list[float]
    notes: list[str]


def final_run(
    static: StaticCost,
    theta: list[float],
    depth: int,
    displacements: np.ndarray,
    steps: list[int],
    settled: bool,
) -> FinalRun:
    """Check dynamic displacements (L, N, 3) at (theta, d, depth) against the reference and
    the static equilibria at (theta, depth): they must agree within 0.1% of the cost."""
    problem = static.problem
    static_ev = static(theta, depth)
    cost = float(sum(static.case_cost(j, u) for j, u in enumerate(displacements)))
    figures = discrepancies(problem, displacements, static.reference)
    notes = []
    if not settled:
        notes.append("the last dynamic run did not settle every load case within max_steps")
    elif abs(cost - static_ev.cost) > max(
        STATIC_AGREEMENT * static_ev.cost, SETTLE_RESOLUTION * static.reference_cost
    ):
        notes.append(
            f"the settled dynamic cost {cost:.6g} m differs from the static cost "
            f"{static_ev.cost:.6g} m by more than {STATIC_AGREEMENT:.1%}: the settle "
            "tolerance stops runs short of equilibrium; a smaller fpm.settle_tolerance helps"
        )
    return FinalRun(
        cost=cost,
        static_cost=float(static_ev.cost),
        settle_steps=[int(s) for s in steps],
        settled=settled,
        relative=figures.relative,
        loaded=figures.loaded,
        h_percent=figures.h_percent,
        notes=notes,
    )


@dataclass
class DampingStage:
    """Two-stage calibration after the chains: polished stiffness, depth and d (JSON-able).

    Attributes:
        theta: polished stiffness parameters, N/m.
        static_cost: their normalised static cost at full depth.
        polish_evaluations: static cost evaluations of the polish.
        depth: resolved penetration depth; full_depth the deepest reachable.
        d: fastest-settling nodal damping, N s/m; d_min the smallest that settles;
            d_guess the critical-damping estimate the search started from.
        damping_runs: dynamic runs of the d search.
        damping_tried: [d, total steps or None] for every d tried.
        final: the check at (theta, d, depth): the d search's runs at d, which are the last
            dynamic run, against the static equilibria.
        seconds: wall time of this stage.
    """

    theta: list[float]
    static_cost: float
    polish_evaluations: int
    depth: int
    full_depth: int
    d: float
    d_min: float
    d_guess: float
    damping_runs: int
    damping_tried: list[tuple[float, int | None]]
    final: FinalRun
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DampingStage:
        return cls(**{**data, "final": FinalRun(**data["final"])})


def stiffness_bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) for the stiffness parameters, N/m: the spec's k bounds, else
    [E h / 100, 10 E h], the same for every family."""
    eh = problem.spec.material.youngs_modulus * problem.h
    k = problem.spec.annealing.bounds.k or (eh / 100, 10 * eh)
    n = len(family_names(problem))
    return np.full(n, float(k[0])), np.full(n, float(k[1]))


def damping_bounds(problem: Problem) -> tuple[float, float]:
    """(lower, upper) for d, N s/m: the spec's, else [0.1, 5] sqrt(E h m)."""
    eh = problem.spec.material.youngs_modulus * problem.h
    scale = float(np.sqrt(eh * problem.solid.masses.mean()))
    d = problem.spec.annealing.bounds.d or (0.1 * scale, 5 * scale)
    return float(d[0]), float(d[1])


def fit_depth(problem: Problem) -> int | None:
    """The depth chains fit at: the spec's integer, or None (every layer) for 'auto'."""
    depth = problem.spec.fpm.depth
    return None if depth == "auto" else int(depth)


def full_depth(problem: Problem) -> int:
    """The deepest perturbed list over the load cases, layers."""
    model = fpm_model(problem)
    return max(model.perturbed_list(j, None).layers for j in range(len(problem.load_cases)))


def reference_displacements(reference: Any) -> np.ndarray:
    """(L, N, 3) from a FemResult (``.displacements``) or an array."""
    return np.asarray(getattr(reference, "displacements", reference), dtype=float)


def run_chain(
    problem: Problem,
    reference: Any,
    chain: int,
    *,
    progress: Progress | None = None,
    checkpoint: Callable[[Checkpoint], None] | None = None,
    resume: Checkpoint | None = None,
) -> ChainResult:
    """One annealing chain, seeded by (spec seed, ``chain``): exactly repeatable.

    Two-stage: over the stiffness parameters, each evaluation a static solve. Paper: over
    (stiffness, d), each evaluation dynamic runs to rest.
    ``progress`` gets {chain, move, moves, temperature, best_cost, current_cost} after each move;
    ``checkpoint`` gets a :class:`~fpm.fitting.annealing.Checkpoint` every few moves, which
    ``resume`` continues from.

    Raises:
        AnnealingError: no acceptable start, with the counts of rejected candidates and what
            to change (e.g. a time step from the lattice's stability estimate).
    """
    t0 = time.perf_counter()
    a = problem.spec.annealing
    disp = reference_displacements(reference)
    depth = fit_depth(problem)
    lower, upper = stiffness_bounds(problem)
    n = len(lower)
    objective: Callable[[list[float]], State]
    initial: list[float] | None = None  # two-stage: the linear estimate
    if a.method == "two-stage":
        static = StaticCost(problem, disp, depth)
        reference_cost = static.reference_cost

        def objective(x: list[float]) -> State:
            ev = static(x)
            return State(list(x), ev.cost / reference_cost, {"rejected": ev.rejected})

        initial = [linear_estimate(static, lower[0], upper[0])] * n if resume is None else None

    else:
        dynamic = CostFunction(problem, disp, depth)
        reference_cost = dynamic.reference_cost
        d_lo, d_hi = damping_bounds(problem)
        lower, upper = np.append(lower, d_lo), np.append(upper, d_hi)
        # An unsettled FPM is still moving: its cost measures a transient, not the model.
        # Such a candidate is rejected like a divergent one, unless the spec asks never to
        # settle (settle_tolerance 0).
        settling = problem.spec.fpm.settle_tolerance > 0

        def objective(x: list[float]) -> State:
            ev = dynamic(x[:n], x[n], stop_unsettled=settling)
            info = {"steps": ev.steps, "settled": ev.settled, "rejected": ev.rejected}
            return State(list(x), ev.cost / reference_cost, info)

    if reference_cost <= 0:
        raise AnnealingError("the reference does not move: nothing to fit")

    def report(info: dict[str, Any]) -> None:
        if progress is not None:
            progress({"chain": chain, **info})

    try:
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
            initial=initial,
        )
    except AnnealingError as e:
        raise AnnealingError(_explain(problem, e), e.rejected, e.tries) from None
    near = [
        NearBest(s.x, s.cost, s.info.get("steps"), s.info.get("settled", True))
        for s in result.near_best
    ]
    return ChainResult(
        chain=chain,
        method=a.method,
        x=list(result.best.x),
        cost=result.best.cost,
        evaluations=result.evaluations,
        accepted=result.accepted,
        history=result.history,
        near_best=near,
        seconds=time.perf_counter() - t0,
    )


def linear_estimate(cost: StaticCost, lower: float, upper: float) -> float:
    """Stage 1's starting k, N/m: the one k whose *linear* response best fits the reference.

    The lattice linearised at rest responds to the loads as ``u(k) = u1 / k`` (u1: the
    response at k = 1 N/m for every spring, one linear solve per load case), so Eq. (2) of the
    linear model, ``sum_ij |s u1_ij - r_ij|`` with ``s = 1/k``, is convex in s; its minimum
    within [lower, upper] (N/m) is found by bounded Brent. Starting there rather than from
    random draws over a 1000x box spares the chains the candidates many times too soft, whose
    large rotations cost tens of Newton iterations at 20,000 nodes. Falls back to the
    geometric mean of the bounds when the linear lattice is not held (an 'axis' lattice).
    """
    p = cost.problem
    unit = spring_stiffness(p, [1.0] * len(family_names(p)))
    try:
        u1 = np.stack(
            [
                cost.solver.linear_response(j, unit, cost.depth, cost.solver.loads(j))
                for j in range(len(p.load_cases))
            ]
        )
    except (SingularStiffnessError, NegativeCurvature):
        return math.sqrt(lower * upper)
    r = cost.reference

    def linear_cost(s: float) -> float:
        return float(np.linalg.norm(s * u1 - r, axis=2).sum())

    s = minimize_scalar(linear_cost, bounds=(1 / upper, 1 / lower), method="bounded")
    return float(min(max(1 / s.x, lower), upper))


def _explain(problem: Problem, error: AnnealingError) -> str:
    """The annealer's failure with its counts and what to change."""
    try:
        from .diagnosis import explain_rejections, stable_time_step
    except ImportError:  # pragma: no cover - the diagnosis module is part of the package
        return str(error)
    lower, upper = stiffness_bounds(problem)
    stiffest = spring_stiffness(problem, upper)
    return explain_rejections(
        error.rejected, error.tries, stable_time_step(problem, stiffest), problem.spec.fpm.dt
    )


def polish(
    cost: StaticCost,
    theta: list[float],
    bounds: tuple[np.ndarray, np.ndarray],
    progress: Progress | None = None,
    *,
    span: float = POLISH_SPAN,
    uniform: int = 1,
    ceilings: list[float] | None = None,
):
    """Bounded local minimisation of the static cost from ``theta`` (log space).

    One parameter: bounded Brent on log k within +-``span``. Several: Nelder-Mead with
    bounds. ``uniform`` > 1 searches one k given to that many families. ``ceilings``: (L,)
    per-case costs, m, not to be exceeded (:func:`constrained_cost`). Returns (theta,
    normalised cost, with any penalty); never worse than the start.
    """
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    y0 = np.log(np.asarray(theta, dtype=float))

    def f(y: np.ndarray) -> float:
        ev = cost(np.repeat(np.exp(np.atleast_1d(y)), uniform))
        if progress is not None:
            progress({"phase": "polish", "evaluations": cost.evaluations})
        return constrained_cost(ev, cost.reference_cost, ceilings)

    start = f(y0)
    a, b = np.maximum(y0 - span, lo), np.minimum(y0 + span, hi)
    if len(y0) == 1:
        r = minimize_scalar(
            lambda y: f(np.array([y])),
            bounds=(a[0], b[0]),
            method="bounded",
            options={"xatol": POLISH_TOLERANCE},
        )
        y, value = np.array([r.x]), float(r.fun)
    else:
        simplex = np.vstack([y0] + [y0 + 0.05 * np.eye(len(y0))[i] for i in range(len(y0))])
        r = minimize(
            f,
            y0,
            method="Nelder-Mead",
            bounds=list(zip(a, b, strict=True)),
            options={
                "xatol": POLISH_TOLERANCE,
                "fatol": 1e-7,
                "initial_simplex": np.clip(simplex, a, b),
                "maxfev": 200,
            },
        )
        y, value = np.asarray(r.x), float(r.fun)
    if value > start:
        return list(np.exp(y0)), start
    return list(np.exp(y)), value


def constrained_cost(ev: Evaluation, scale: float, ceilings: list[float] | None) -> float:
    """Eq. (2) over ``scale`` (the reference cost), plus CEILING_PENALTY times every load
    case's excess over its ceiling (m, also over ``scale``); 1e6 for no equilibrium.

    A families fit is polished under ceilings at the single-k fit's case costs: it may lower
    the total only by improving load cases, never by trading one case's accuracy for another's
    against one k (an exact penalty: a weight above the 1:1 rate at which the sum trades cases
    keeps the minimum within the ceilings)."""
    if not math.isfinite(ev.cost):
        return 1e6
    excess = 0.0
    if ceilings is not None:
        excess = sum(max(c - top, 0.0) for c, top in zip(ev.case_costs, ceilings, strict=True))
    return (ev.cost + CEILING_PENALTY * excess) / scale


def resolve_depth(
    cost: StaticCost, theta: list[float], tolerance: float, progress: Progress | None = None
) -> tuple[int, int, dict[int, list[float]]]:
    """Depth 'auto': the smallest depth whose static cost, in every load case, is within
    ``tolerance`` (relative) of full depth's, at the stiffness ``theta`` fitted at full depth.

    Galloping down from full depth (full - 1, full - 2, full - 4, ...) until a depth fails, then
    bisection between it and the last that passed; each probe is a static solve per load case,
    and the returned depth always passes the test. The answer is usually close to full depth
    (32 of 33 layers on the organ at h = 3 mm: 2 probes where bisection from 0 takes 6, each of
    the deepest, costliest lists). Returns (depth, full depth, {depth probed: case costs, m}).
    """
    full = cost(theta, None)
    deepest = full_depth(cost.problem)
    probed = {deepest: full.case_costs}

    def passes(depth: int) -> bool:
        if progress is not None:
            progress({"phase": "depth", "depth": depth})
        ev = cost(theta, depth)
        probed[depth] = ev.case_costs
        return math.isfinite(ev.cost) and all(
            c <= f * (1 + tolerance) for c, f in zip(ev.case_costs, full.case_costs, strict=True)
        )

    fail, ok, gap = -1, deepest, 1
    while ok - gap > fail:
        if not passes(ok - gap):
            fail = ok - gap
            break
        ok, gap = ok - gap, 2 * gap
    while ok - fail > 1:
        mid = (fail + ok) // 2
        if passes(mid):
            ok = mid
        else:
            fail = mid
    return ok, deepest, probed


def fit_damping(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    *,
    progress: Progress | None = None,
) -> DampingStage:
    """Two-stage, after the chains: polish the best stiffness (at the depth the chains fitted
    at), resolve the depth, find d.

    With families, the polish starts from the better of the chains' best and the best single
    k (every family at one k, a 1-D search): one k is a point of the families' space, so a
    family fit never ends worse than the single-k fit of the same problem.
    """
    t0 = time.perf_counter()
    disp = reference_displacements(reference)
    best = min(chains, key=lambda c: c.cost)
    cost = StaticCost(problem, disp, fit_depth(problem))
    if progress is not None:
        progress({"phase": "polish"})
    bounds = stiffness_bounds(problem)
    start, ceilings = best.x, None
    if len(start) > 1:
        uniform, _ = polish(
            cost, [float(np.exp(np.mean(np.log(start))))], (bounds[0][:1], bounds[1][:1]),
            progress, span=UNIFORM_SPAN, uniform=len(start),
        )  # fmt: skip
        ceilings = cost(uniform * len(start)).case_costs
        chains_best = constrained_cost(cost(start), cost.reference_cost, ceilings)
        if constrained_cost(cost(uniform * len(start)), cost.reference_cost, None) < chains_best:
            start = uniform * len(start)
    span = UNIFORM_SPAN if len(start) > 1 else POLISH_SPAN
    theta, _ = polish(cost, start, bounds, progress, span=span, ceilings=ceilings)
    static_cost = cost(theta).cost / cost.reference_cost
    evaluations = cost.evaluations
    depth = fit_depth(problem)
    if progress is not None:
        progress({"phase": "depth"})
    if depth is None:
        depth, deepest, _ = resolve_depth(
            cost, theta, problem.spec.fpm.auto_depth_tolerance, progress
        )
    else:
        deepest = full_depth(problem)
    static = np.stack(
        [cost.displacements(theta, j, depth).displacements for j in range(len(problem.load_cases))]
    )
    if progress is not None:
        progress({"phase": "damping"})
    stiffness = spring_stiffness(problem, theta)
    fit = fastest_damping(
        problem,
        stiffness,
        depth,
        damping_bounds(problem),
        damping_guesses(problem, cost.solver, stiffness, depth, static),
        progress=None if progress is None else (lambda i: progress({"phase": "damping", **i})),
    )
    final = final_run(cost, theta, depth, fit.displacements, fit.steps, settled=True)
    return DampingStage(
        theta=[float(t) for t in theta],
        static_cost=float(static_cost),
        polish_evaluations=evaluations,
        depth=int(depth),
        full_depth=int(deepest),
        d=fit.d,
        d_min=fit.d_min,
        d_guess=fit.guess,
        damping_runs=fit.runs,
        damping_tried=fit.tried,
        final=final,
        seconds=time.perf_counter() - t0,
    )


def damping_guesses(
    problem: Problem,
    solver: StaticSolver,
    stiffness: np.ndarray,
    depth: int,
    static: np.ndarray,
) -> tuple[float, float]:
    """Two critical-damping estimates, N s/m (:mod:`fpm.fitting.damping`): from the static shapes
    ``static`` (L, N, 3), and from the shapes their inertia deflects the linear lattice into
    (one inverse iteration); the first twice when the lattice at rest is not held (an 'axis'
    lattice is a mechanism there)."""
    upper = critical_damping(problem, static)
    masses = problem.solid.masses[None, :, None]
    try:
        inertia = np.stack(
            [
                solver.linear_response(j, stiffness, depth, masses[0] * static[j])
                for j in range(len(problem.load_cases))
            ]
        )
        return critical_damping(problem, inertia, masses * static), upper
    except (SingularStiffnessError, NegativeCurvature):
        return upper, upper


def pick_paper_state(chains: list[ChainResult]) -> tuple[list[float], float]:
    """Paper method: among the states within 0.1% of the best cost over every chain, the one
    that settles in the fewest total steps (counts within 5% are equally fast, and then the
    cheapest wins). Returns (stiffness parameters, d)."""
    best_cost = min(c.cost for c in chains)
    candidates = [
        s for c in chains for s in c.near_best if s.cost <= best_cost * (1 + EQUALLY_GOOD)
    ]
    if any(s.settled for s in candidates):
        candidates = [s for s in candidates if s.settled]
    fewest = min(sum(s.steps or ()) for s in candidates)
    fast = [s for s in candidates if sum(s.steps or ()) <= fewest * (1 + SAME_SPEED)]
    pick = min(fast, key=lambda s: (s.cost, sum(s.steps or ())))
    return list(pick.x[:-1]), float(pick.x[-1])


def finalize(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    damping: DampingStage | None = None,
    *,
    warnings: list[str] | None = None,
) -> CalibrationResult:
    """The calibration result: a last dynamic run at (stiffness, d, depth) and its figures.

    Two-stage needs ``damping`` (from :func:`fit_damping`); the paper method picks its state
    from the chains and resolves depth 'auto' on static equilibria.
    """
    if not chains:
        raise ValueError("no chain results")
    t0 = time.perf_counter()
    disp = reference_displacements(reference)
    method = chains[0].method
    if method == "two-stage":
        if damping is None:
            raise ValueError("the two-stage method needs the damping stage's result")
        theta, d, depth, deepest = damping.theta, damping.d, damping.depth, damping.full_depth
        final = damping.final
    else:
        static = StaticCost(problem, disp, None)
        theta, d = pick_paper_state(chains)
        asked = fit_depth(problem)
        if asked is None:
            depth, deepest, _ = resolve_depth(static, theta, problem.spec.fpm.auto_depth_tolerance)
        else:
            depth, deepest = asked, full_depth(problem)
        dynamic = CostFunction(problem, disp, depth)
        runs = [dynamic.displacements(theta, d, j) for j in range(len(problem.load_cases))]
        final = final_run(
            static,
            theta,
            depth,
            np.stack([r.displacements for r in runs]),
            [r.steps for r in runs],
            all(r.settled for r in runs),
        )
    winner = min(chains, key=lambda c: c.cost)
    stiffness = stiffness_dict(problem, theta)
    m = problem.solid.masses
    from ..fem.reference import reference_label

    return CalibrationResult(
        reference=reference_label(problem.spec),
        method=method,
        k=float(theta[0]),
        stiffness=stiffness,
        d=float(d),
        d_min=None if damping is None else damping.d_min,
        depth=int(depth),
        full_depth=int(deepest),
        cost=final.cost,
        static_cost=final.static_cost,
        relative_discrepancy=final.relative,
        loaded_discrepancy=final.loaded,
        discrepancy_h=final.h_percent,
        settle_steps=final.settle_steps,
        settled=final.settled,
        evaluations=sum(c.evaluations for c in chains)
        + (damping.polish_evaluations if damping else 0),
        damping_runs=damping.damping_runs if damping else 0,
        seconds={
            "stiffness": max(c.seconds for c in chains),
            "damping": damping.seconds if damping else 0.0,
            "finalize": time.perf_counter() - t0,
        },
        history=winner.history,
        h=problem.h,
        node_mass={
            "min": float(m.min()),
            "max": float(m.max()),
            "mean": float(m.mean()),
            "total": float(m.sum()),
        },
        warnings=list(warnings or []) + final.notes,
        chains=[
            ChainSummary(chain=c.chain, x=c.x, cost=c.cost, evaluations=c.evaluations)
            for c in chains
        ],
    )


def check_reference(problem: Problem, reference: Any) -> list[str]:
    """Units sanity of the FEM reference (:func:`fpm.fitting.diagnosis.check_reference`): raises
    on a reference no small-strain solid gives, returns warnings."""
    from .diagnosis import check_reference as check

    return check(problem, reference_displacements(reference))


def calibrate(
    problem: Problem,
    *,
    chains: int | None = None,
    progress: Progress | None = None,
    reference: Any = None,
    threads: int | None = None,
) -> CalibrationResult:
    """Fit stiffness, d and depth for ``problem`` in-process.

    Args:
        problem: from :func:`fpm.load_problem`.
        chains: number of annealing chains (None = the spec's).
        progress: called with {phase, chain, move, moves, temperature, best_cost, ...};
            phases fem, annealing, polish, depth, damping, finalize.
        reference: FEM result or (L, N, 3) displacements (None = the spec's
            ``reference.displacements`` if given, else solve the FEM now).
        threads: chains run at once (None = one per core).

    Raises:
        fpm.fitting.diagnosis.UnitsError: the FEM reference moves more than the solid's smallest
            extent (almost always a units mistake), before any annealing.
        AnnealingError: the search cannot start (with what to change).
    """
    n = problem.spec.annealing.chains if chains is None else chains
    if n < 1:
        raise ValueError("chains must be >= 1")
    if reference is None:
        from ..fem.reference import reference_for

        if progress is not None:
            progress({"phase": "fem"})
        reference = reference_for(problem)
    warnings = check_reference(problem, reference)

    def one(chain: int) -> ChainResult:
        cb = None if progress is None else (lambda info: progress({"phase": "annealing", **info}))
        return run_chain(problem, reference, chain, progress=cb)

    workers = min(n, threads or os.cpu_count() or 1)
    if workers == 1:
        results = [one(c) for c in range(n)]
    else:
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(one, range(n)))
    damping = None
    if problem.spec.annealing.method == "two-stage":
        damping = fit_damping(problem, reference, results, progress=progress)
    if progress is not None:
        progress({"phase": "finalize"})
    return finalize(problem, reference, results, damping, warnings=warnings)
