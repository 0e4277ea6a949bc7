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
from ..dynamics.stability import time_step
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.spec import lame_constants
from ..model.stiffness import (
    FLOOR,
    continuum_start,
    family_names,
    has_volume,
    model_stiffness,
    spring_stiffness,
    stiffness_dict,
    volume_stiffness,
)
from .annealing import AnnealingError, Checkpoint, Schedule, State, anneal
from .cost import CostFunction, Evaluation, StaticCost, discrepancies, dynamic_time_step
from .damping import critical_damping, fastest_damping
from .reduced import ReducedLinearModel, fit_reduced
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
        dt: the time step d was fitted at, s (the spec's, or 'auto' resolved at theta).
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
    dt: float
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
    """(lower, upper) for the stiffness parameters: the spec's k bounds, else
    [E h / 100, 10 E h] N/m, the same for every family. families+volume: each family from
    FLOOR mu h (its 'zero') to the top of the k bounds, and kappa in [FLOOR mu, 10 (lambda +
    2 mu)] Pa (kappa >= 0: for nu < 1/4 it stays at its floor, see
    :func:`fpm.model.stiffness.continuum_start`)."""
    eh = problem.spec.material.youngs_modulus * problem.h
    k = problem.spec.annealing.bounds.k or (eh / 100, 10 * eh)
    n = len(family_names(problem))
    if not has_volume(problem):
        return np.full(n, float(k[0])), np.full(n, float(k[1]))
    m = problem.spec.material
    mu, lam = lame_constants(m.youngs_modulus, m.poisson_ratio)
    low = min(float(k[0]), FLOOR * mu * problem.h)
    lower = np.append(np.full(n - 1, low), FLOOR * mu)
    upper = np.append(np.full(n - 1, float(k[1])), 10 * (lam + 2 * mu))
    return lower, upper


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


def reference_displacements(reference: Any, problem: Problem | None = None) -> np.ndarray:
    """(L, N, 3) from a FemResult (``.displacements``) or an array: the load cases' part
    (the reference also holds the validation cases after them, :func:`validation_reference`)."""
    every = np.asarray(getattr(reference, "displacements", reference), dtype=float)
    return every if problem is None else every[: len(problem.load_cases)]


def validation_reference(reference: Any, problem: Problem) -> np.ndarray | None:
    """(V, N, 3) the reference of the validation cases, or None if it holds none (a reference
    of the load cases only)."""
    every = np.asarray(getattr(reference, "displacements", reference), dtype=float)
    n, v = len(problem.load_cases), len(problem.validation_cases)
    if not v or len(every) < n + v:
        return None
    return every[n : n + v]


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
    disp = reference_displacements(reference, problem)
    depth = fit_depth(problem)
    lower, upper = stiffness_bounds(problem)
    n = len(lower)
    objective: Callable[[list[float]], State]
    initial: list[float] | None = None  # two-stage: the linear estimate
    reduced: ReducedLinearModel | None = None
    if a.method == "two-stage":
        static = StaticCost(problem, disp, depth)
        reference_cost = static.reference_cost
        if has_volume(problem) and resume is None:
            # families+volume: the chain anneals the reduced linear model (fpm.fitting.reduced),
            # then the defect-corrected reduced fit lands on the static equilibria's minimum.
            reduced = ReducedLinearModel(
                static, list(np.clip(continuum_start(problem), lower, upper))
            )

        def objective(x: list[float]) -> State:
            if reduced is not None:
                value = reduced(np.asarray(x))
                rejected = "" if math.isfinite(value) else "no equilibrium"
                return State(list(x), value / reference_cost, {"rejected": rejected})
            ev = static(x)
            return State(list(x), ev.cost / reference_cost, {"rejected": ev.rejected})

        if resume is not None:
            initial = None
        elif has_volume(problem):  # the closed form is the natural start (fpm.model.stiffness)
            initial = list(np.clip(continuum_start(problem), lower, upper))
        else:
            initial = [linear_estimate(static, lower[0], upper[0])] * n

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
    best_x, best_cost, evaluations = list(result.best.x), result.best.cost, result.evaluations
    if reduced is not None:
        best_x, best_cost, reduced = fit_reduced(static, best_x, (lower, upper), reduced)
        evaluations += reduced.solves
    return ChainResult(
        chain=chain,
        method=a.method,
        x=best_x,
        cost=best_cost,
        evaluations=evaluations,
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
        from ..dynamics.stability import stable_time_step, time_step
        from .diagnosis import explain_rejections
    except ImportError:  # pragma: no cover - the diagnosis module is part of the package
        return str(error)
    lower, upper = stiffness_bounds(problem)
    stiffest = model_stiffness(problem, upper)
    return explain_rejections(
        error.rejected,
        error.tries,
        stable_time_step(problem, stiffest),
        time_step(problem, stiffest),
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
    disp = reference_displacements(reference, problem)
    best = min(chains, key=lambda c: c.cost)
    cost = StaticCost(problem, disp, fit_depth(problem))
    if progress is not None:
        progress({"phase": "polish"})
    bounds = stiffness_bounds(problem)
    start, ceilings = best.x, None
    if len(start) > 1 and not has_volume(problem):
        uniform, _ = polish(
            cost, [float(np.exp(np.mean(np.log(start))))], (bounds[0][:1], bounds[1][:1]),
            progress, span=UNIFORM_SPAN, uniform=len(start),
        )  # fmt: skip
        ceilings = cost(uniform * len(start)).case_costs
        chains_best = constrained_cost(cost(start), cost.reference_cost, ceilings)
        if constrained_cost(cost(uniform * len(start)), cost.reference_cost, None) < chains_best:
            start = uniform * len(start)
    span = UNIFORM_SPAN if len(start) > 1 else POLISH_SPAN
    if has_volume(problem):  # the chains' defect-corrected fit is the polish
        theta = list(start)
    else:
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
    stiffness = model_stiffness(problem, theta)
    dt = time_step(problem, stiffness)
    fit = fastest_damping(
        problem,
        stiffness,
        depth,
        damping_bounds(problem),
        damping_guesses(problem, cost.solver, stiffness, depth, static),
        dt=dt,
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
        dt=dt,
        damping_runs=fit.runs,
        damping_tried=fit.tried,
        final=final,
        seconds=time.perf_counter() - t0,
    )


def damping_guesses(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
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
    disp = reference_displacements(reference, problem)
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
    dt = damping.dt if damping is not None else dynamic_time_step(problem)
    # Full depth reaches every node from any load (a validation load elsewhere needs it).
    validation = validate(problem, reference, theta, None if depth >= deepest else depth)
    m = problem.solid.masses
    from ..fem.reference import reference_label

    return CalibrationResult(
        reference=reference_label(problem.spec),
        method=method,
        stiffness_mode=problem.spec.fpm.stiffness,
        k=float(theta[0]),
        stiffness=stiffness,
        volume_stiffness=volume_stiffness(problem, theta),
        dt=dt,
        validation_cases=[c.name for c in problem.validation_cases],
        validation_relative_discrepancy=validation.relative,
        validation_discrepancy_h=validation.h_percent,
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
        warnings=list(warnings or []) + final.notes + validation.notes + mode_notes(problem),
        chains=[
            ChainSummary(chain=c.chain, x=c.x, cost=c.cost, evaluations=c.evaluations)
            for c in chains
        ],
    )


@dataclass
class Validation:
    """The validation cases at the fitted parameters: relative and % of h per case, and notes."""

    relative: list[float]
    h_percent: list[float]
    notes: list[str]


def validate(problem: Problem, reference: Any, theta: list[float], depth: int | None) -> Validation:
    """The validation cases (never in the cost) at the fitted stiffness ``theta`` and ``depth``
    (None: every layer), against their reference: their static equilibria, the state a settled
    run reaches (d and dt decide only how fast)."""
    if not problem.validation_cases:
        return Validation([], [], [])
    truth = validation_reference(reference, problem)
    if truth is None:
        return Validation(
            [], [], ["the reference holds no validation cases: they were not evaluated"]
        )
    checked = problem.validation_problem()
    cost = StaticCost(checked, truth, depth)
    solved = [cost.displacements(theta, j) for j in range(len(checked.load_cases))]
    figures = discrepancies(checked, np.stack([e.displacements for e in solved]), truth)
    notes = [
        f"validation case '{checked.load_cases[e.load_case].name}': no static equilibrium "
        f"({e.message}): its figure is of an unconverged state"
        for e in solved
        if not e.converged
    ]
    return Validation(figures.relative, figures.h_percent, notes)


def mode_notes(problem: Problem) -> list[str]:
    """What the user should know about the stiffness mode (families+volume below nu 1/4)."""
    m = problem.spec.material
    mu, lam = lame_constants(m.youngs_modulus, m.poisson_ratio)
    if has_volume(problem) and lam < mu:
        return [
            f"Poisson's ratio {m.poisson_ratio:g} < 1/4: the volume term would need a negative "
            f"kappa (lambda - mu = {lam - mu:.4g} Pa), which can let cells collapse; kappa is "
            "held at its floor, so the lattice stays near nu = 1/4 (as the spring-only models)"
        ]
    return []


def check_reference(problem: Problem, reference: Any) -> list[str]:
    """Units sanity of the FEM reference (:func:`fpm.fitting.diagnosis.check_reference`): raises
    on a reference no small-strain solid gives, returns warnings."""
    from .diagnosis import check_reference as check

    return check(problem, reference_displacements(reference, problem))


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
    problem.cache.pop("reduced_units", None)  # stage 1's shared matrices (fpm.fitting.reduced)
    damping = None
    if problem.spec.annealing.method == "two-stage":
        damping = fit_damping(problem, reference, results, progress=progress)
    if progress is not None:
        progress({"phase": "finalize"})
    return finalize(problem, reference, results, damping, warnings=warnings)
