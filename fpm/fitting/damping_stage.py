"""Stage 2 of the two-stage calibration, after the chains: polished stiffness, depth, (the
stiffness field,) then d.

:func:`fit_damping` (the service's damping job) polishes the chains' best stiffness theta (N/m;
kappa in Pa) on static equilibria (:func:`fpm.fitting.stiffness_stage.polish`; with families,
from the better of the chains' best and the best single k), resolves depth 'auto'
(:func:`fpm.fitting.depth.resolve_depth`; the paper method's finalize uses it too), with
``fpm.stiffness: "field"`` fits the per-cell field at that depth
(:func:`fpm.fitting.field.fit_field`), and finds the fastest-settling nodal damping d (N s/m)
at the dt of theta (or of the field):
:func:`find_damping`: :func:`fpm.fitting.damping.fastest_damping` from the d the lattice's
slowest modes predict (:mod:`fpm.dynamics.modes`; where the lattice at rest has none, from two
critical-damping estimates, :func:`damping_guesses`), fpm.max_steps 'auto' resolved from the
prediction. Its result, :class:`DampingStage`, is JSON-able and carries the final
check (:class:`fpm.fitting.validation.FinalRun`): the runs of the fastest d are the calibration's
last dynamic run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from ..dynamics.eigen import Modes, single_threaded_blas
from ..dynamics.equilibrium import StaticSolver
from ..dynamics.modes import predict_damping
from ..dynamics.modes_ahead import ModesAhead
from ..dynamics.settle import by_distance, case_distances, nominal_distance
from ..dynamics.stability import stable_time_step, time_step
from ..dynamics.step_caps import FALLBACK_STEPS, auto_max_steps
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.stiffness import has_volume, is_extended, is_field, model_stiffness
from .bounds import damping_bounds, fit_depth, full_depth, stiffness_bounds
from .cost import StaticCost
from .damping import DampingFit, critical_damping, fastest_damping
from .defect_correction import fit_reduced
from .depth import resolve_depth
from .diagnosis import SMALL_STRAIN
from .field import fit_field
from .lockstep import Spread
from .reduced import ReducedBasis, first_basis
from .stiffness_stage import (
    POLISH_SPAN,
    UNIFORM_SPAN,
    ChainResult,
    Progress,
    constrained_cost,
    polish,
)
from .validation import FinalRun, Validation, final_run, reference_displacements, validate


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
            for full depth), :class:`fpm.fitting.validation.Validation` as a dict with that
            "depth"; solved beside the stage, on a thread or by another worker (None: left to
            finalize).
        settle: each load case's settle stiffness, N/m, its runs settled on (the distance
            criterion, :mod:`fpm.dynamics.settle`); None: the force criterion.
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

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DampingStage:
        return cls(**{**data, "final": FinalRun(**data["final"])})


@dataclass(frozen=True)
class DampingPlan:
    """What one dynamic run of the d search needs besides d and its cap (JSON-able): the
    stiffness theta (N/m; kappa Pa) the model is built from (:func:`model_stiffness`), the
    depth, the time step dt (s), whether a stiffness field replaced theta's model (its
    runs are not handed to other processes), each load case's settle stiffness (N/m, the
    distance criterion of :mod:`fpm.dynamics.settle`; None: the force criterion), and each
    load case's settle distance where the runs settle on the target criterion (None: they do
    not; the static equilibria they settle towards travel beside the plan:
    :func:`find_damping`'s ``static``)."""

    theta: list[float]
    depth: int
    dt: float
    field: bool = False
    settle: list[float] | None = None
    distance: list[float] | None = None


SAME_FIT = 0.001
"""Material regions, anisotropy: chains within this fraction of the best cost fit equally well
(:func:`chain_to_polish`)."""


def chain_to_polish(problem: Problem, chains: list[ChainResult]) -> ChainResult:
    """The chain whose best state stage 2 takes: the cheapest; with material regions or a
    transversely isotropic material, among the chains within :data:`SAME_FIT` of it, the one
    with the longest time step. A region the loads barely strain (a stiff inclusion) leaves
    its parameters free to drift upwards at no cost, and a drifted kappa shortens dt, and with
    it the settle steps, several times (the paper method picks the fastest-settling of its
    equally good states alike)."""
    best = min(chains, key=lambda c: c.cost)
    if not is_extended(problem):
        return best
    near = [c for c in chains if c.cost <= best.cost * (1 + SAME_FIT)]
    return max(near, key=lambda c: stable_time_step(problem, model_stiffness(problem, c.x)))


Validator = Callable[[list[float], "int | None"], "Future[Validation]"]
"""Starts the validation cases' static solves (:func:`fpm.fitting.validation.validate`) at
(theta, the depth finalize validates at) somewhere else than this thread, e.g. on another
worker (:class:`worker.spread.ValidationTask`); their answer does not depend on where."""


def fit_damping(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    *,
    progress: Progress | None = None,
    spread: Callable[[DampingPlan, np.ndarray | None], Spread | None] | None = None,
    basis: ReducedBasis | None = None,
    validator: Validator | None = None,
) -> DampingStage:
    """Two-stage, after the chains: polish the best stiffness (at the depth the chains fitted
    at), resolve the depth, find d.

    families+volume (and field): the polish is the defect-corrected reduced fit
    (:func:`fpm.fitting.defect_correction.fit_reduced`) from the best chain's state on
    ``basis``, the calibration's first basis (built here when None: the same bits); its last
    round's static equilibria are the warm starts of the stage's static solves at the answer.

    ``spread``: given the :class:`DampingPlan` (what a run needs besides d and its caps) and
    the static equilibria (L, N, 3) m its runs settle towards (None: none),
    the :class:`~fpm.fitting.lockstep.Spread` that runs the predicted d's load cases and the
    d tried next over other processes (None: here); the worker hands them to free workers
    (:mod:`worker.spread`). The answer does not depend on it. ``validator``: where the
    validation cases are solved (None: on a thread beside the stage).

    With families, the polish starts from the better of the chains' best and the best single
    k (every family at one k, a 1-D search): one k is a point of the families' space, so a
    family fit never ends worse than the single-k fit of the same problem.
    """
    side = ThreadPoolExecutor(1, thread_name_prefix="validation")
    try:

        def beside(theta: list[float], depth: int | None) -> Future[Validation]:
            return side.submit(validate, problem, reference, theta, depth)

        validating = beside if validator is None else validator
        stage = _fit_damping(problem, reference, chains, progress, spread, validating, basis)
    except BaseException:  # a failed or canceled stage does not wait for its validation
        side.shutdown(wait=False, cancel_futures=True)
        raise
    side.shutdown()
    return stage


def _fit_damping(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    progress: Progress | None,
    spread: Callable[[DampingPlan, np.ndarray | None], Spread | None] | None,
    validator: Validator,
    basis: ReducedBasis | None,
) -> DampingStage:
    """:func:`fit_damping`'s work; ``validator`` starts the validation cases' static solves
    while the stage goes on (they need the final stiffness and depth, not d), once the depth is
    chosen and the depth probes' systems are dropped, beside the slowest modes' prediction:
    started beside the depth probes, the validation's systems and theirs would sit in memory
    together, at the calibration's peak. A field's model is validated by finalize."""
    t0 = time.perf_counter()
    disp = reference_displacements(reference, problem)
    best = chain_to_polish(problem, chains)
    validating: dict[int | None, Future[Validation]] = {}
    checks = bool(problem.validation_cases) and not is_field(problem)
    cost = StaticCost(problem, disp, fit_depth(problem))
    if progress is not None:
        progress({"phase": "polish"})
    bounds = stiffness_bounds(problem)
    solves = 0
    # the slowest modes, found beside the polish from its second round (their hierarchy is
    # the polish's); the prediction takes those whose hierarchy the polish kept
    ahead = ModesAhead(cost.solver, fit_depth(problem))
    if has_volume(problem):  # the defect-corrected reduced fit is the polish
        with single_threaded_blas():
            theta, _, solves = fit_reduced(
                cost, basis or first_basis(problem), best.x, bounds, progress,
                after_round=ahead.start,
            )  # fmt: skip
        problem.cache.reduced_units = None  # its unit matrices are not needed again
    else:
        theta = _polish(cost, best.x, bounds, progress)
    static_cost = cost(theta).cost / cost.reference_cost
    evaluations = cost.evaluations + solves
    depth = fit_depth(problem)
    deepest = full_depth(problem)
    if problem.spec.fpm.depth == "auto":
        if progress is not None:
            progress({"phase": "depth"})
        depth, deepest, _ = resolve_depth(
            cost, theta, problem.spec.fpm.auto_depth_tolerance, progress
        )
    elif depth is None:
        depth = deepest
    cost.solver.keep_only(depth)  # the depth probes' systems are not asked again
    checked = None if depth >= deepest else depth  # as finalize validates
    if checks and checked not in validating:
        validating[checked] = validator(list(theta), checked)
    stiffness = model_stiffness(problem, theta)
    field = None
    if is_field(problem):  # the per-cell field on theta (the four parameters if it is refused)
        field = fit_field(problem, disp, cost.solver, theta, depth, progress=progress)
        stiffness = field.stiffness(problem)
    static = np.stack(
        [
            cost.displacements(stiffness, j, depth).displacements
            for j in range(len(problem.load_cases))
        ]
    )
    if progress is not None:
        progress({"phase": "damping"})
    dt = time_step(problem, stiffness)
    plan = DampingPlan([float(t) for t in theta], int(depth), dt, field is not None)
    fit, plan = find_damping(
        problem,
        cost.solver,
        stiffness,
        depth,
        static,
        dt,
        None if progress is None else (lambda i: progress({"phase": "damping", **i})),
        plan,
        spread,
        disp,
        ahead.modes(depth),
    )
    final = final_run(
        cost, stiffness, depth, fit.displacements, fit.steps, settled=True,
        residuals=fit.residuals, settle=plan.settle, statics=static, distances=plan.distance,
    )  # fmt: skip
    validation = None
    if checks:
        found = validating[checked].result()
        validation = {**asdict(found), "depth": checked}
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
        d_predicted=fit.predicted,
        max_steps=fit.max_steps,
        field=None if field is None else field.to_dict(),
        validation=validation,
        settle=plan.settle,
    )


def _polish(
    cost: StaticCost,
    start: list[float],
    bounds: tuple[np.ndarray, np.ndarray],
    progress: Progress | None,
) -> list[float]:
    """The polished stiffness from the chains' best ``start`` (not families+volume): with
    families, from the better of it and the best single k, under that k's case costs as
    ceilings (:func:`fpm.fitting.stiffness_stage.polish`)."""
    ceilings = None
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
    return list(theta)


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


def find_damping(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int,
    static: np.ndarray,
    dt: float,
    progress: Any = None,
    plan: DampingPlan | None = None,
    spread: Callable[[DampingPlan, np.ndarray | None], Spread | None] | None = None,
    reference: np.ndarray | None = None,
    modes: dict[bytes, Modes] | None = None,
) -> tuple[DampingFit, DampingPlan]:
    """The fastest-settling d at (``stiffness``, ``depth``, ``dt`` s), from ``static`` (L, N,
    3) the static equilibria, m, ``reference`` (L, N, 3) the reference's displacements at the
    lattice nodes, m (the settle distances 'auto' read: :func:`fpm.dynamics.settle.case_distances`;
    None: the nominal distance), and ``plan`` (None: made of ``stiffness``' parameters) with
    each case's settle stiffness: the distance criterion's (:mod:`fpm.dynamics.settle`) read
    from the modes of the prediction, or None for the force criterion (the spec names a
    settle_tolerance, or there are no modes). The search of
    :func:`fpm.fitting.damping.fastest_damping`
    started at the d the lattice's slowest modes predict
    (:func:`fpm.dynamics.modes.predict_damping`), with fpm.max_steps 'auto' taken from the
    steps predicted there (:func:`fpm.dynamics.modes.auto_max_steps`). Where the lattice at
    rest has no modes to predict from (a mechanism, e.g. 'axis' springs) or no d settles in
    the reduced steps, from the two critical-damping estimates of :func:`damping_guesses`,
    'auto' then being FALLBACK_STEPS. ``spread``: given the plan and the static equilibria its
    runs settle towards (the target criterion; None: not), runs the search's runs over
    other processes (:func:`fpm.fitting.damping.fastest_damping`); ``modes``: the slowest
    modes already found (:class:`fpm.dynamics.modes_ahead.ModesAhead`). Returns the fit and the
    plan its runs followed."""
    bounds = damping_bounds(problem)
    asked = problem.spec.fpm.max_steps
    why = strain_notes(problem, static, reference)
    if plan is None:
        plan = DampingPlan([float(t) for t in stiffness.parameters()], int(depth), dt)
    distance = None
    if by_distance(problem.spec):  # the target criterion: the runs settle towards static
        distance = case_distances(problem.spec, static, reference)
    try:
        prediction, models = predict_damping(
            problem, solver, stiffness, depth, dt, bounds, static, distances=distance,
            modes=modes,
        )  # fmt: skip
    except (ValueError, SingularStiffnessError, NegativeCurvature, np.linalg.LinAlgError):
        guesses = damping_guesses(problem, solver, stiffness, depth, static)
        cap = FALLBACK_STEPS if asked == "auto" else int(asked)
        fit = fastest_damping(
            problem, stiffness, depth, bounds, guesses, dt=dt, progress=progress, max_steps=cap,
            auto=asked == "auto", spread=None if spread is None else spread(plan, None), why=why,
        )  # fmt: skip
        return fit, plan
    targets = None
    if distance is not None:
        each = [nominal_distance(problem.spec) * m.mode_stiffness for m in models]
        plan = replace(plan, settle=each, distance=distance)
        targets = static
    cap = auto_max_steps(prediction.steps) if asked == "auto" else int(asked)
    fit = fastest_damping(
        problem, stiffness, depth, bounds, (prediction.d, prediction.d), dt=dt,
        progress=progress, prediction=prediction, models=models, max_steps=cap,
        auto=asked == "auto", spread=None if spread is None else spread(plan, targets),
        settle=plan.settle, targets=targets, distances=plan.distance, why=why,
    )  # fmt: skip
    return fit, plan


def strain_notes(problem: Problem, static: np.ndarray, reference: np.ndarray | None) -> list[str]:
    """Per load case, how far its loads take the solid, for a case that cannot settle: the
    largest spring strain |l / L - 1| of its static equilibrium ``static`` (L, N, 3) m and the
    largest displacement of the reference ``reference`` (L, N, 3) m (None: not said) as a
    share of the solid's smallest bounding-box extent."""
    springs, rest = problem.solid.springs, problem.rest_lengths
    extents = np.ptp(problem.nodes, axis=0)
    extent = float(extents[extents > 0].min())
    notes = []
    for j, u in enumerate(static):
        x = problem.nodes + u
        strain = float(
            np.abs(np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=1) / rest - 1).max()
        )
        note = f"its static equilibrium strains a spring by {100 * strain:.0f}%"
        if reference is not None:
            moved = float(np.linalg.norm(reference[j], axis=1).max()) / extent
            note += (
                f", and the FEM moves a node by {100 * moved:.0f}% of the solid's smallest "
                f"extent ({extent:.3g} m)"
            )
            if moved > SMALL_STRAIN:
                note += ", far outside the small strain its linear reference assumes"
        notes.append(note)
    return notes
