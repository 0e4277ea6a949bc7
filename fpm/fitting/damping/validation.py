"""The fit checked against its FEM reference, outside the cost: the last dynamic run against
the reference and the static equilibria (:func:`final_run`), the validation cases at the fitted
stiffness (:func:`validate`), and a load case run again as the fit's last run ran it
(:func:`replayed_run`, the web view's profile)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...dynamics.equilibrium import Equilibrium, static_equilibrium
from ...dynamics.settle import (
    PROMISE,
    estimated_distance,
    measured_distance,
    nodal_size,
    nominal_distance,
    run_criterion,
)
from ...dynamics.simulation import SimulationResult, fpm_model, simulate
from ...dynamics.step_caps import fixed_max_steps
from ...fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ...model.problem import Problem
from ...model.stiffness import fitted_theta, model_stiffness
from ..cost import StaticCost, Theta, discrepancies
from ..reference import validation_reference
from .settings import DEFAULT, DampingSettings


@dataclass
class FinalRun:
    """The last dynamic run at (stiffness, d, depth) against the reference and the statics.

    Attributes:
        cost: Eq. (2) of the dynamic run, m; static_cost: of the static equilibria, m.
        settle_steps: (L,) steps to settle; settled: every load case settled.
        relative, loaded, h_percent: the discrepancies (:class:`fpm.fitting.cost.Discrepancies`).
        notes: warnings (did not settle; dynamic and static costs disagree; a settled state
            further from its static equilibrium than promised).
        settle_estimated: (L,) per load case, the settled state's distance from its static
            equilibrium as its run estimated it (:func:`fpm.dynamics.settle.estimated_distance`,
            relative to its displacement); None without the distance criterion.
        settle_measured: (L,) the same distance measured against the static equilibrium
            (:func:`fpm.dynamics.settle.measured_distance`); None without the distance
            criterion.
        settle_distance: (L,) the distance each case was promised within (its settle
            distance); None without the distance criterion.
        compliance: (L,) the load compliance ratio of each settled state
            (:func:`fpm.fitting.cost.compliance_ratio`); empty in a stage stored before it.
    """

    cost: float
    static_cost: float
    settle_steps: list[int]
    settled: bool
    relative: list[float]
    loaded: list[float]
    h_percent: list[float]
    notes: list[str]
    settle_estimated: list[float] | None = None
    settle_measured: list[float] | None = None
    settle_distance: list[float] | None = None
    compliance: list[float | None] = field(default_factory=list)


def final_run(
    static: StaticCost,
    theta: Theta,
    depth: int,
    displacements: np.ndarray,
    steps: list[int],
    settled: bool,
    *,
    residuals: list[float] | None = None,
    settle: list[float] | None = None,
    statics: np.ndarray | None = None,
    distances: list[float] | None = None,
    settings: DampingSettings = DEFAULT,
) -> FinalRun:
    """Check dynamic displacements (L, N, 3) m at (theta, d, depth) against the reference and
    the static equilibria at (theta, depth). On the force criterion (``settle`` None) the two
    costs must agree to ``settings.static_agreement`` (or ``settle_resolution`` of the
    reference cost). On the distance criterion (``settle`` (L,) N/m; ``residuals`` (L,) the
    runs' last 2-norm residuals, N, or on the target criterion (``distances`` given) their
    reach, m) each settled state must be within PROMISE times its settle distance of its
    static equilibrium (``statics`` (L, N, 3) m; None: solved here), measured."""
    problem = static.problem
    static_ev = static(theta, depth)
    cost = float(sum(static.case_cost(j, u) for j, u in enumerate(displacements)))
    figures = discrepancies(problem, displacements, static.reference)
    notes = []
    estimated = measured = None
    if settled and settle is not None and residuals is not None:
        if statics is None:
            statics = np.stack(
                [static.displacements(theta, j, depth).displacements for j in range(len(steps))]
            )
        if distances is not None:
            estimated = [r / nodal_size(u) for r, u in zip(residuals, statics, strict=True)]
        else:
            distances = [nominal_distance(problem.spec)] * len(steps)
            estimated = [
                estimated_distance(r, float(np.linalg.norm(u)), s / share)
                for r, u, s, share in zip(residuals, displacements, settle, distances, strict=True)
            ]
        measured = [measured_distance(u, v) for u, v in zip(displacements, statics, strict=True)]
        far = [
            f"{case.name} {m:.2%} (promised {PROMISE * share:.2%})"
            for case, m, share in zip(problem.load_cases, measured, distances, strict=True)
            if m > PROMISE * share
        ]
        if far:
            notes.append(
                f"settled states further from the static equilibrium than promised, relative "
                f"to their displacement: {', '.join(far)}; a smaller fpm.settle_distance helps"
            )
    if not settled:
        notes.append("the last dynamic run did not settle every load case within max_steps")
    elif estimated is None and abs(cost - static_ev.cost) > max(
        settings.static_agreement * static_ev.cost,
        settings.settle_resolution * static.reference_cost,
    ):
        notes.append(
            f"the settled dynamic cost {cost:.6g} m differs from the static cost "
            f"{static_ev.cost:.6g} m by more than {settings.static_agreement:.1%}: the settle "
            "tolerance stops runs short of equilibrium; a smaller fpm.settle_tolerance helps"
        )
    return FinalRun(
        cost=cost, static_cost=float(static_ev.cost), settle_steps=[int(s) for s in steps],
        settled=settled, relative=figures.relative, loaded=figures.loaded,
        h_percent=figures.h_percent, notes=notes, settle_estimated=estimated,
        settle_measured=measured, settle_distance=None if measured is None else distances,
        compliance=figures.compliance,
    )  # fmt: skip


@dataclass
class Validation:
    """The validation cases at the fitted parameters: relative and % of h per case, notes, and
    the load compliance ratio per case (:func:`fpm.fitting.cost.compliance_ratio`)."""

    relative: list[float]
    h_percent: list[float]
    notes: list[str]
    compliance: list[float | None] = field(default_factory=list)


def validate(
    problem: Problem,
    reference: Any,
    theta: Theta,
    depth: int | None,
    *,
    geometry: bool = True,
    settings: DampingSettings = DEFAULT,
) -> Validation:
    """The validation cases (never in the cost) at the fitted stiffness ``theta`` and ``depth``
    (None: every layer), against their reference: their static equilibria, the state a settled
    run reaches (d and dt decide only how fast). ``geometry``: with :func:`geometry_notes`."""
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
    if geometry and not notes:
        notes = geometry_notes(cost, truth, theta, solved, figures.relative, settings)
    return Validation(figures.relative, figures.h_percent, notes, figures.compliance)


def geometry_notes(
    cost: StaticCost,
    truth: np.ndarray,
    theta: Theta,
    solved: list[Equilibrium],
    relative: list[float],
    settings: DampingSettings = DEFAULT,
) -> list[str]:
    """A note for each validation case of ``cost``'s problem (the validation cases as load
    cases) whose ``relative`` figure, %, exceeds by more than ``settings.geometry_gap`` points
    that of the same model linearised at rest (CG started from its equilibrium in ``solved``)
    against ``truth`` (V, N, 3) m: the springs' change of geometry, which a finer lattice does
    not remove (docs/explanation/organs-conforming.md, *Large loads*)."""
    checked = cost.problem
    stiffness = model_stiffness(checked, theta)
    try:
        linear = [
            cost.solver.linear_response(j, stiffness, cost.depth, cost.solver.loads(j),
                                        guess=e.displacements, rtol=settings.geometry_tolerance)
            for j, e in enumerate(solved)
        ]  # fmt: skip
    except (SingularStiffnessError, NegativeCurvature):  # not held when linearised
        return []
    small = discrepancies(checked, np.stack(linear), truth).relative
    return [
        f"validation case '{case.name}': {big:.1f}% at its loads, {little:.1f}% under small "
        f"loads: {big - little:.1f} points are the springs' change of geometry under these loads "
        "(they rotate and stretch; the FEM reference is linear, small strain), which a finer "
        "lattice does not remove"
        for case, big, little in zip(checked.load_cases, relative, small, strict=True)
        if big - little > settings.geometry_gap
    ]


def replayed_run(problem: Problem, record: dict[str, Any], load_case: int) -> SimulationResult:
    """Load case ``load_case`` run from rest as the fit's last run ran it (the web view's
    profile), from its stored ``record`` (a calibration result as a dict): its stiffness, d,
    depth, dt, cap and settle criterion (where it names no settle distances, as
    :func:`fpm.simulate` settles)."""
    theta = fitted_theta(problem, record)
    distances, settle = record.get("settle_distance"), record.get("settle_stiffness")
    if not distances or not settle:
        return simulate(problem, k=theta, d=record["d"], depth=record["depth"], load_case=load_case)
    depth = record["depth"]
    static = static_equilibrium(problem, k=theta, depth=depth, load_case=load_case)
    criterion = run_criterion(
        problem.spec, settle[load_case], static.displacements, distances[load_case]
    )
    cap = record.get("max_steps") or fixed_max_steps(problem.spec.fpm.max_steps)
    return fpm_model(problem).run(
        load_case, k=model_stiffness(problem, theta), d=record["d"], depth=depth,
        dt=record["dt"], max_steps=int(cap), settle=criterion,
    )  # fmt: skip
