"""Choosing d: the nodal damping that settles fastest at the fitted stiffness (docs/physics.md).

:func:`fit_damping` chooses it: the prediction of the lattice's slowest modes (or, without one,
the critical-damping estimates of :mod:`fpm.fitting.damping.critical`), then the search of
:func:`fpm.fitting.damping.search.fastest_damping`, with the plan its runs follow
(:class:`DampingPlan`) and, for a case that cannot settle, how far its loads take the solid
(:func:`strain_notes`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ...dynamics.eigen import Modes
from ...dynamics.equilibrium import StaticSolver
from ...dynamics.modes import Prediction, predict_damping
from ...dynamics.settle import by_distance, case_distances, nominal_distance
from ...dynamics.step_caps import AUTO_CEILING, FALLBACK_STEPS, auto_max_steps
from ...fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ...model.forces import Stiffness
from ...model.problem import Problem
from ..bounds import damping_bounds
from ..diagnosis import SMALL_STRAIN
from .critical import damping_guesses
from .lockstep import (
    Spread,
)
from .search import DampingFit, fastest_damping
from .settings import DEFAULT, DampingSettings
from .unsettled import Hopeless


@dataclass(frozen=True)
class DampingPlan:
    """What one dynamic run of the d search needs besides d and its cap (JSON-able): the
    stiffness theta (N/m; kappa Pa) the model is built from (:func:`model_stiffness`), the
    depth, the time step dt (s), whether a stiffness field replaced theta's model (its
    runs are not handed to other processes), each load case's settle stiffness (N/m, the
    distance criterion of :mod:`fpm.dynamics.settle`; None: the force criterion), and each
    load case's settle distance where the runs settle on the target criterion (None: they do
    not; the static equilibria they settle towards travel beside the plan:
    :func:`fit_damping`'s ``static``)."""

    theta: list[float]
    depth: int
    dt: float
    field: bool = False
    settle: list[float] | None = None
    distance: list[float] | None = None


def fit_damping(
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
    settings: DampingSettings = DEFAULT,
) -> tuple[DampingFit, DampingPlan]:
    """The fastest-settling d at (``stiffness``, ``depth``, ``dt`` s), from ``static`` (L, N,
    3) the static equilibria, m, ``reference`` (L, N, 3) the reference's displacements at the
    lattice nodes, m (the settle distances 'auto' read: :func:`fpm.dynamics.settle.case_distances`;
    None: the nominal distance), and ``plan`` (None: made of ``stiffness``' parameters) with
    each case's settle stiffness: the distance criterion's (:mod:`fpm.dynamics.settle`) read
    from the modes of the prediction, or None for the force criterion (the spec names a
    settle_tolerance, or there are no modes). The search of
    :func:`fpm.fitting.damping.search.fastest_damping`
    started at the d the lattice's slowest modes predict
    (:func:`fpm.dynamics.modes.predict_damping`), with fpm.max_steps 'auto' taken from the
    steps predicted there (:func:`fpm.dynamics.modes.auto_max_steps`). Where the lattice at
    rest has no modes to predict from (a mechanism, e.g. 'axis' springs) or no d settles in
    the reduced steps, from the two critical-damping estimates of :func:`damping_guesses`,
    'auto' then being FALLBACK_STEPS. ``spread``: given the plan and the static equilibria its
    runs settle towards (the target criterion; None: not), runs the search's runs over
    other processes (:func:`fastest_damping`); ``modes``: the slowest
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
            settings=settings,
        )  # fmt: skip
        return fit, plan
    targets = None
    if distance is not None:
        each = [nominal_distance(problem.spec) * m.mode_stiffness for m in models]
        plan = replace(plan, settle=each, distance=distance)
        targets = static
    if asked == "auto" and max(prediction.steps) > AUTO_CEILING:
        raise too_slow(prediction, dt)
    cap = auto_max_steps(prediction.steps) if asked == "auto" else int(asked)
    fit = fastest_damping(
        problem, stiffness, depth, bounds, (prediction.d, prediction.d), dt=dt,
        progress=progress, prediction=prediction, models=models, max_steps=cap,
        auto=asked == "auto", spread=None if spread is None else spread(plan, targets),
        settle=plan.settle, targets=targets, distances=plan.distance, why=why,
        settings=settings,
    )  # fmt: skip
    return fit, plan


def too_slow(prediction: Prediction, dt: float) -> Hopeless:
    """The error of a lattice whose fastest d is predicted to need more than fpm.max_steps
    'auto' allows (:data:`fpm.dynamics.step_caps.AUTO_CEILING`), raised before any run."""
    most = max(prediction.steps)
    error = Hopeless(
        f"the fastest d the lattice's slowest modes predict ({prediction.d:.4g} N s/m) needs "
        f"{most:,.0f} steps to settle its slowest load case ({most * dt:.3g} s simulated at dt "
        f"{dt:.3g} s), over the {AUTO_CEILING:,} fpm.max_steps 'auto' allows: so slow a "
        "lattice is not interactive in this kernel (a coarser or better-shaped lattice settles "
        "in fewer steps; fpm.max_steps set to a number searches anyway)"
    )
    error.predicted = prediction.d
    return error


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
