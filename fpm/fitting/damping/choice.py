"""Choosing d, the nodal damping that settles fastest at the fitted stiffness: the prediction
of the lattice's slowest modes (or, without one, the critical-damping estimates), then the
search (:func:`fpm.fitting.damping.search.fastest_damping`), with the plan its runs follow.
The critical-damping estimates (:func:`damping_guesses`) are where the search starts when the
modes predict nothing (docs/explanation/physics/damping-prediction.md)."""

from __future__ import annotations

import math
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
from .lockstep import Spread
from .search import DampingFit, fastest_damping
from .settings import DEFAULT, DampingSettings
from .unsettled import Hopeless


@dataclass(frozen=True)
class DampingPlan:
    """What one dynamic run of the d search needs besides d and its cap (JSON-able): the
    stiffness theta (N/m; kappa Pa), the depth, dt (s), whether a stiffness field replaced
    theta's model (its runs stay in this process), each load case's settle stiffness (N/m;
    None: the force criterion) and settle distance (None: the runs do not settle towards the
    static equilibria, which travel beside the plan)."""

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
    """The fastest-settling d at (``stiffness``, ``depth``, ``dt`` s), and the plan its runs
    followed (``plan``; None: made of ``stiffness``' parameters).

    ``static`` (L, N, 3) m: the static equilibria; ``reference`` (L, N, 3) m: the reference at
    the lattice nodes, which settle distance 'auto' reads (None: the nominal distance);
    ``modes``: the slowest modes already found (:class:`fpm.dynamics.modes_ahead.ModesAhead`).
    The search starts at the d the modes predict (:func:`fpm.dynamics.modes.predict_damping`),
    fpm.max_steps 'auto' from the steps predicted there; where the lattice at rest has no modes
    (a mechanism) or nothing settles in the reduced steps, from the two critical-damping
    estimates, 'auto' then FALLBACK_STEPS. ``spread``: given the plan and the static
    equilibria its runs settle towards (None: not), what runs the search's runs elsewhere."""
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
    """The error raised before any run when the predicted fastest d needs more steps than
    fpm.max_steps 'auto' allows (:data:`fpm.dynamics.step_caps.AUTO_CEILING`)."""
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
    """Per load case, how far its loads take the solid, said of a case that cannot settle: the
    largest spring strain of its static equilibrium ``static`` (L, N, 3) m and the largest
    displacement of ``reference`` (L, N, 3) m (None: not said) against the solid's smallest
    bounding-box extent."""
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


def critical_damping(
    problem: Problem, displacements: np.ndarray, loads: np.ndarray | None = None
) -> float:
    """Critical damping estimate, N s/m, from shapes (L, N, 3) held by ``loads`` (L, N, 3), N
    (None: each load case's forces, so the shapes are static displacements).

    The geometric mean over load cases of ``2 omega (u^T M u) / (u^T u)`` with Rayleigh's
    ``omega^2 = f.u / (u^T M u)``.
    """
    m = problem.solid.masses
    estimates = []
    for j, case in enumerate(problem.load_cases):
        u = displacements[j]
        f = case.dense(problem.n_nodes) if loads is None else loads[j]
        mu2 = float(np.einsum("n,ni,ni->", m, u, u))
        u2 = float(np.einsum("ni,ni->", u, u))
        work = float(np.einsum("ni,ni->", f, u))
        if mu2 > 0 and work > 0:
            estimates.append(2 * math.sqrt(work / mu2) * mu2 / u2)
    if not estimates:
        raise ValueError("no load case moves: cannot estimate the damping")
    return float(np.exp(np.mean(np.log(estimates))))


def damping_guesses(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int,
    static: np.ndarray,
) -> tuple[float, float]:
    """Two critical-damping estimates, N s/m: from the static shapes ``static`` (L, N, 3) m and
    from the shapes their inertia deflects the linear lattice into (one inverse iteration); the
    first twice where the lattice at rest is not held (a mechanism)."""
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
