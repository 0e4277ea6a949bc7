"""Stage 2's driver, :func:`fit_stage` (the service's damping job): the polish, depth 'auto',
the validation cases started beside the stage, with ``fpm.stiffness: "field"`` the per-cell
field, then d and the final check of its runs. Its result, :class:`DampingStage`, is JSON-able.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ...dynamics.modes_ahead import ModesAhead
from ...dynamics.stability import time_step
from ...model.problem import Problem
from ...model.stiffness import is_field, model_stiffness
from ..bounds import fit_depth, full_depth
from ..cost import StaticCost
from ..field import fit_field
from ..reduced import ReducedBasis
from ..reference import reference_displacements
from ..step_budget import budget_depth
from ..stiffness_stage import ChainResult, Progress
from .choice import DampingPlan, damping_guesses, fit_damping
from .depth import resolve_depth
from .lockstep import Spread
from .polish import chain_to_polish, polish_stiffness
from .search import DampingFit
from .settings import DEFAULT, DampingSettings
from .unsettled import DampingError
from .validation import FinalRun, Validation, final_run, validate


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
        d_predicted: the fastest d predicted from the modes before any run, N s/m (None:
            no prediction; the search started from the critical-damping estimates).
        max_steps: the cap on each run's steps: the spec's, or 'auto' resolved.
        field: ``fpm.stiffness: "field"``: the field fit
            (:meth:`fpm.fitting.field.FieldStage.to_dict`), fitted at depth on the polished
            theta before d; d, dt and ``final`` are then those of the model it returns.
        validation: the validation cases at (theta, the depth finalize validates at: None
            for full depth), :class:`fpm.fitting.damping.validation.Validation` as a dict with that
            "depth"; solved beside the stage, on a thread or by another worker (None: left to
            finalize).
        settle: each load case's settle stiffness, N/m, its runs settled on (the distance
            criterion, :mod:`fpm.dynamics.settle`); None: the force criterion.
        step_budget: ``fpm.step_budget_us``: the depth its region step allows and what was
            measured (:func:`fpm.fitting.step_budget.budget_depth`); None: no budget.
        unfitted: why no d was fitted (the search's :class:`DampingError`, with the dt and
            cap the product chose: :func:`chose_the_runs`): d is then the critical-damping
            estimate (:func:`unfitted_damping`), the final run the static equilibria,
            unsettled; None: d was fitted.
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
    d_predicted: float | None = None
    max_steps: int | None = None
    field: dict[str, Any] | None = None
    validation: dict[str, Any] | None = None
    settle: list[float] | None = None
    step_budget: dict[str, Any] | None = None
    unfitted: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DampingStage:
        return cls(**{**data, "final": FinalRun(**data["final"])})


def chose_the_runs(problem: Problem) -> bool:
    """Whether the product chose the d search's dt and step cap (``fpm.dt`` and
    ``fpm.max_steps`` both 'auto'): then a search that settles nothing keeps the static fit
    (:func:`unfitted_damping`); a dt or cap the spec names is the user's to change."""
    return problem.spec.fpm.dt == "auto" and problem.spec.fpm.max_steps == "auto"


def unfitted_damping(
    problem: Problem,
    solver: Any,
    stiffness: Any,
    depth: int,
    static: np.ndarray,
    predicted: float | None = None,
) -> DampingFit:
    """Where the d search finds no d that settles: the static fit stands, with d the fastest d
    the modes ``predicted`` (N s/m), else the geometric mean of the two critical-damping
    estimates, and the static equilibria ``static`` (L, N, 3) m as the settled states."""
    d = predicted
    if d is None:
        low, high = damping_guesses(problem, solver, stiffness, depth, static)
        d = float(np.sqrt(low * high))
    cases = len(problem.load_cases)
    return DampingFit(d, [0] * cases, static, d, d, 0, predicted=predicted, residuals=[0.0] * cases)


Validator = Callable[[list[float], "int | None"], "Future[Validation]"]
"""Starts the validation cases' static solves at (theta, the depth finalize validates at)
elsewhere than this thread (:class:`worker.spread.ValidationTask`)."""


def fit_stage(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    *,
    progress: Progress | None = None,
    spread: Callable[[DampingPlan, np.ndarray | None], Spread | None] | None = None,
    basis: ReducedBasis | None = None,
    validator: Validator | None = None,
    settings: DampingSettings = DEFAULT,
) -> DampingStage:
    """Two-stage, after the chains: polish the best stiffness (at the depth the chains fitted
    at; families+volume: the defect-corrected reduced fit on ``basis``, built when None),
    resolve the depth, find d. ``spread``: given the plan of the runs
    (:class:`~fpm.fitting.damping.choice.DampingPlan`) and the static equilibria (L, N, 3) m
    they settle towards (None: none), what runs the search's runs over other processes
    (None: here; :mod:`worker.spread`); ``validator``: where the validation cases are solved
    (None: on a thread beside the stage). Neither changes the answer.
    """
    side = ThreadPoolExecutor(1, thread_name_prefix="validation")
    try:

        def beside(theta: list[float], depth: int | None) -> Future[Validation]:
            return side.submit(validate, problem, reference, theta, depth, settings=settings)

        validating = beside if validator is None else validator
        stage = _fit_stage(problem, reference, chains, progress, spread, validating, basis,
                           settings)  # fmt: skip
    except BaseException:  # a failed or canceled stage does not wait for its validation
        side.shutdown(wait=False, cancel_futures=True)
        raise
    side.shutdown()
    return stage


def _fit_stage(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    progress: Progress | None,
    spread: Callable[[DampingPlan, np.ndarray | None], Spread | None] | None,
    validator: Validator,
    basis: ReducedBasis | None,
    settings: DampingSettings,
) -> DampingStage:
    """:func:`fit_stage`'s work. The validation cases start once the depth is chosen and the
    depth probes' systems are dropped (so the two never sit in memory together); a field's
    model is validated by finalize."""
    t0 = time.perf_counter()
    disp = reference_displacements(reference, problem)
    best = chain_to_polish(problem, chains, settings)
    checks = bool(problem.validation_cases) and not is_field(problem)
    cost = StaticCost(problem, disp, fit_depth(problem))
    # the slowest modes, found beside the polish from its second round (their hierarchy is
    # the polish's); the prediction takes those whose hierarchy the polish kept
    ahead = ModesAhead(cost.solver, fit_depth(problem))
    theta, solves = polish_stiffness(problem, cost, best.x, progress, basis, ahead)
    static_cost = cost(theta).cost / cost.reference_cost
    evaluations = cost.evaluations + solves
    depth = fit_depth(problem)
    deepest = full_depth(problem)
    if problem.spec.fpm.depth == "auto":
        if progress is not None:
            progress({"phase": "depth"})
        depth, deepest, _ = resolve_depth(cost, theta, problem.spec.fpm.auto_depth_tolerance,
                                          progress)  # fmt: skip
    elif depth is None:
        depth = deepest
    budget = None
    if problem.spec.fpm.step_budget_us is not None:  # the deepest list the frame allows
        if progress is not None:
            progress({"phase": "step budget"})
        at_theta = model_stiffness(problem, theta)
        budget = budget_depth(
            problem, at_theta, time_step(problem, at_theta), problem.spec.fpm.step_budget_us, depth
        )
        depth = budget["depth"]
    cost.solver.keep_only(depth)  # the depth probes' systems are not asked again
    checked = None if depth >= deepest else depth  # as finalize validates
    validating = validator(list(theta), checked) if checks else None
    stiffness = model_stiffness(problem, theta)
    field = None
    if is_field(problem):  # the per-cell field on theta (the four parameters if it is refused)
        field = fit_field(problem, disp, cost.solver, theta, depth, progress=progress)
        stiffness = field.stiffness(problem)
    cases = range(len(problem.load_cases))
    static = np.stack([cost.displacements(stiffness, j, depth).displacements for j in cases])
    if progress is not None:
        progress({"phase": "damping"})
    dt = time_step(problem, stiffness)
    plan = DampingPlan([float(t) for t in theta], int(depth), dt, field is not None)
    unfitted = None
    try:
        fit, plan = fit_damping(
            problem, cost.solver, stiffness, depth, static, dt,
            None if progress is None else (lambda i: progress({"phase": "damping", **i})),
            plan, spread, disp, ahead.modes(depth), settings,
        )  # fmt: skip
    except DampingError as error:
        if not chose_the_runs(problem):  # the spec's dt or cap: its advice is the answer
            raise
        unfitted = str(error)  # the product's own dt and cap: the static fit stands
        fit = unfitted_damping(problem, cost.solver, stiffness, depth, static, error.predicted)
    final = final_run(
        cost, stiffness, depth, fit.displacements, fit.steps, settled=unfitted is None,
        residuals=fit.residuals, settle=plan.settle, statics=static, distances=plan.distance,
        settings=settings,
    )  # fmt: skip
    validation = None
    if validating is not None:
        validation = {**asdict(validating.result()), "depth": checked}
    return DampingStage(
        theta=[float(t) for t in theta], static_cost=float(static_cost),
        polish_evaluations=evaluations, depth=int(depth), full_depth=int(deepest), d=fit.d,
        d_min=fit.d_min, d_guess=fit.guess, dt=dt, damping_runs=fit.runs,
        damping_tried=fit.tried, final=final, seconds=time.perf_counter() - t0,
        d_predicted=fit.predicted, max_steps=fit.max_steps,
        field=None if field is None else field.to_dict(), validation=validation,
        settle=None if unfitted else plan.settle, step_budget=budget, unfitted=unfitted,
    )  # fmt: skip
