"""Stage 1 of the calibration: the stiffness, fitted by one annealing chain, later polished.

:func:`run_chain` runs one seeded chain of simulated annealing (:mod:`fpm.fitting.annealing`, log
space) inside the box of :mod:`fpm.fitting.bounds`:

- two-stage (the default): over the stiffness parameters theta (k, or one k per spring family,
  N/m; then kappa, Pa, for families+volume), each candidate's cost Eq. (2) taken at its static
  equilibria (:class:`fpm.fitting.cost.StaticCost`). The chain starts from the linear estimate
  (:func:`linear_estimate`); families+volume start from the continuum start and anneal the
  reduced linear model (:mod:`fpm.fitting.reduced`) on the calibration's first basis (built
  once, handed to every chain); its defect-corrected fit, from the best chain's state, is the
  damping stage's polish;
- paper: over (theta, d) jointly (d in N s/m), each candidate run dynamically to rest
  (:class:`fpm.fitting.cost.CostFunction`); an unsettled candidate is rejected.

Costs are normalised by the reference cost (the cost of an FPM that does not move). A chain's
outcome, :class:`ChainResult` (its best x and cost, and the states near it, :class:`NearBest`), is
JSON-able: the service runs each chain as a job and stores it.

After the chains (two-stage, :func:`fpm.fitting.damping.stage.fit_stage`), :func:`polish`
refines the best state by a bounded local minimisation of the static cost in log theta
(families+volume: :func:`fpm.fitting.defect_correction.fit_reduced` instead); a families fit
is polished under ceilings, the single-k fit's per-case costs (:func:`constrained_cost`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from ..dynamics.eigen import single_threaded_blas
from ..dynamics.settle import force_tolerance
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.problem import Problem
from ..model.stiffness import (
    family_names,
    has_volume,
    model_stiffness,
    spring_stiffness,
)
from .annealing import AnnealingError, Checkpoint, Schedule, State, anneal
from .bounds import damping_bounds, fit_depth, stiffness_bounds
from .cost import CostFunction, Evaluation, StaticCost
from .reduced import ReducedBasis, ReducedLinearModel, chain_start, first_basis
from .reference import reference_displacements

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
"""The stages' progress callback: one dict per step ({phase, ...}; a chain's {chain, move, ...})."""


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
        cost: its normalised cost (Eq. 2 / reference cost; families+volume: of the reduced
            linear model).
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


def run_chain(
    problem: Problem,
    reference: Any,
    chain: int,
    *,
    progress: Progress | None = None,
    checkpoint: Callable[[Checkpoint], None] | None = None,
    resume: Checkpoint | None = None,
    basis: ReducedBasis | None = None,
) -> ChainResult:
    """One annealing chain, seeded by (spec seed, ``chain``): exactly repeatable.

    Two-stage: over the stiffness parameters, each evaluation a static solve; families+volume:
    each evaluation the reduced linear model on ``basis``, the calibration's first basis
    (:func:`fpm.fitting.reduced.first_basis`, built here when None: the same bits), no
    full solve at all. Paper: over (stiffness, d), each evaluation dynamic runs to rest.
    ``progress`` gets {chain, move, moves, temperature, best_cost, current_cost} after each move;
    ``checkpoint`` gets a :class:`~fpm.fitting.annealing.Checkpoint` every few moves, which
    ``resume`` continues from.

    Raises:
        AnnealingError: no acceptable start, with the counts of rejected candidates and what
            to change (e.g. a time step from the lattice's stability estimate).
    """
    # a chain shares the cores with the other chains: a threaded BLAS only waits
    with single_threaded_blas():
        return _run_chain(problem, reference, chain, progress, checkpoint, resume, basis)


def _run_chain(
    problem: Problem,
    reference: Any,
    chain: int,
    progress: Progress | None,
    checkpoint: Callable[[Checkpoint], None] | None,
    resume: Checkpoint | None,
    basis: ReducedBasis | None,
) -> ChainResult:
    """:func:`run_chain`'s work."""
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
        if has_volume(problem):
            # families+volume: the chain anneals the reduced linear model (fpm.fitting.reduced)
            # on the calibration's first basis; the damping stage's defect-corrected fit from
            # the best chain's state lands on the static equilibria's minimum.
            reduced = ReducedLinearModel.of(problem, basis or first_basis(problem), disp)

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
            initial = chain_start(problem)
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
        settling = force_tolerance(problem.spec) > 0

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
    within [lower, upper] (N/m) is found by bounded Brent. Falls back to the
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
