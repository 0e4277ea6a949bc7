"""What the lattice's slowest modes predict for the FPM step: the nodal damping d that settles
every load case in the fewest steps, before any run: the slowest modes
(:func:`fpm.dynamics.eigen.lowest_modes`), the reduced step of each load case on them
(:func:`reduced_steps`, :mod:`fpm.dynamics.reduced_step`), and the d with the fewest predicted
steps summed over the load cases (:func:`fastest_predicted`)
(docs/explanation/physics/damping-prediction.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..fem.linear_solver import SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from .eigen import DENSE_UP_TO, MODES, Modes, lowest_modes, single_threaded_blas
from .equilibrium import StaticSolver
from .reduced_step import CHECK_EVERY, NEVER, StepModel, step_model
from .settle import by_distance, force_tolerance, mode_stiffness, nodal_size, nominal_distance


@dataclass
class Prediction:
    """The fastest-settling d predicted from the modes before any run, N s/m, and the (L,)
    steps predicted per load case there."""

    d: float
    steps: list[float]


def total_steps(models: list[StepModel], d: float, cap: int, budget: float = NEVER) -> float:
    """Predicted steps summed over the load cases at d; inf if one never settles, or once the
    sum passes ``budget``."""
    total = 0.0
    for model in models:
        total += model.steps(d, int(min(cap, budget - total + CHECK_EVERY)))
        if not total <= budget:
            return NEVER
    return total


def fastest_predicted(
    models: list[StepModel], bounds: tuple[float, float], cap: int, *, points: int = 25
) -> tuple[float, list[float]]:
    """The d in ``bounds`` (N s/m) with the fewest predicted steps summed over ``models``: a
    log grid of ``points`` (a point is given up once its sum passes twice the best so far),
    then golden-section refinement around its best to 0.5%. Returns (d, predicted steps per
    model). Raises ValueError if no d of the grid settles."""
    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    grid = np.linspace(lo, hi, points)
    totals: list[float] = []
    for y in grid:
        budget = 2 * min(totals, default=NEVER)
        totals.append(total_steps(models, math.exp(y), cap, budget))
    best = int(np.argmin(totals))
    if not math.isfinite(totals[best]):
        raise ValueError("no d in the bounds settles in the reduced step")
    a, b = grid[max(best - 1, 0)], grid[min(best + 1, points - 1)]
    golden = (math.sqrt(5) - 1) / 2
    known = {float(grid[best]): totals[best]}

    def value(y: float) -> float:
        if y not in known:
            known[y] = total_steps(models, math.exp(y), cap)
        return known[y]

    c, e = b - golden * (b - a), a + golden * (b - a)
    while b - a > math.log(1.005):
        if value(c) <= value(e):
            b, e = e, c
            c = b - golden * (b - a)
        else:
            a, c = c, e
            e = a + golden * (b - a)
    y = min(known, key=lambda v: (known[v], v))
    d = math.exp(y)
    return d, [m.steps(d, cap) for m in models]


def predict_damping(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    bounds: tuple[float, float],
    static: np.ndarray | None = None,
    *,
    cap: int = 1_000_000,
    count: int = MODES,
    distances: list[float] | None = None,
    modes: dict[bytes, Modes] | None = None,
) -> tuple[Prediction, list[StepModel]]:
    """The predicted fastest d of ``problem``'s load cases at ``stiffness``, ``depth`` and
    ``dt``, within ``bounds`` (N s/m), and the reduced steps it came from. ``static`` (L, N, 3)
    m: the static equilibria (None: the modes' linear response); ``distances``: each case's
    settle distance towards them (None: the spec's); ``modes``: those already found, keyed as
    :func:`reduced_steps` keys them.

    Raises:
        ValueError: no d in the bounds settles in the reduced steps (e.g. a tolerance of 0).
        SingularStiffnessError: the lattice at rest is not held (a mechanism).
    """
    found: dict[bytes, Modes] = {} if modes is None else dict(modes)
    with single_threaded_blas():
        models = reduced_steps(
            problem, solver, stiffness, depth, dt, static, count=count, modes=found,
            distances=distances,
        )  # fmt: skip
        d, steps = fastest_predicted(models, bounds, cap)
    return Prediction(d, steps), models


def reduced_steps(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    static: np.ndarray | None = None,
    *,
    count: int = MODES,
    cases: list[int] | None = None,
    modes: dict[bytes, Modes] | None = None,
    distances: list[float] | None = None,
) -> list[StepModel]:
    """:class:`StepModel` of each load case (``cases``: those only) at ``stiffness``,
    ``depth``, ``dt``; the modes of each distinct list computed once and kept in ``modes``
    (keyed by the list's nodes; pass the same dict again for the same stiffness). On the
    distance criteria of :mod:`fpm.dynamics.settle`: with ``static`` (L, N, 3) m the target
    criterion at ``distances`` (None: the spec's nominal distance), else the bound (1) at
    the nominal distance.

    Raises:
        SingularStiffnessError: the lattice at rest has a mode without stiffness.
    """
    found = {} if modes is None else modes
    spec = problem.spec
    models = []
    for j in range(len(problem.load_cases)) if cases is None else cases:
        system, _ = solver.system(j, depth)
        key = system.free.tobytes()
        params = system.parameters(stiffness)
        if key not in found:
            kept = solver.multigrid(system) if 3 * system.n_free > DENSE_UP_TO else None
            hierarchy = None
            if kept is not None:
                # above DENSE_UP_TO the modes read the hierarchy's own levels (the finest
                # level's matrix is the stiffness), so the tangent at rest is assembled only
                # where there is no hierarchy yet
                hierarchy = kept.hierarchy
                tangent = hierarchy.levels[0].A
            else:
                tangent = system.tangent(np.zeros((system.n_free, 3)), params, modified=True)
                if 3 * system.n_free > DENSE_UP_TO:
                    hierarchy = solver._linear_hierarchy(system, tangent).hierarchy
            try:
                lowest = lowest_modes(
                    tangent, problem.solid.masses[system.free], count, hierarchy=hierarchy,
                    free=system.free,
                )  # fmt: skip
            except np.linalg.LinAlgError as e:
                raise SingularStiffnessError(f"the modes: {e}") from None
            found[key] = lowest
        if not np.all(found[key].w2 > 1e-12 * max(float(found[key].w2.max()), 1e-300)):
            raise SingularStiffnessError("the lattice at rest has a mode without stiffness")
        plist = solver.lists.get(problem.load_cases[j].nodes, depth)
        loads = solver.loads(j)
        distance = by_distance(spec)
        if distance:  # fpm.dynamics.settle: (1) at the modes' response, or (2) at static's
            shapes = found[key]
            if static is None:  # the modes' linear response, on the distance criterion (1)
                f = loads[system.free].ravel()
                moved = shapes.shapes @ ((shapes.shapes.T @ f) / shapes.w2)
                force = (
                    nominal_distance(spec)
                    * mode_stiffness(shapes.w2, shapes.shapes)
                    * float(np.linalg.norm(moved))
                )
            else:  # the target criterion (2): its reach, m
                share = nominal_distance(spec) if distances is None else distances[j]
                force = share * nodal_size(static[j])
        else:
            force = force_tolerance(spec) * float(np.linalg.norm(loads[plist.order], axis=1).max())
        models.append(
            step_model(
                system,
                stiffness,
                plist.order,
                found[key],
                problem.solid.masses,
                dt,
                loads,
                force,
                None if static is None else static[j],
                distance,
            )  # fmt: skip
        )
    return models
