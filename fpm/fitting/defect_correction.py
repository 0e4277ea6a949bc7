"""The defect-corrected fit of families+volume (:mod:`fpm.fitting.reduced`, the damping
stage's polish): rounds of reduced fits corrected by the nonlinear defect.

The model is nonlinear (springs rotate, cells change volume), and a probe's load moves its node
a good fraction of h. Each round therefore (1) minimises the reduced cost (Nelder-Mead in log
theta from the last minimiser), (2) solves the full linear model at the minimiser and adds that
response to the basis, (3) solves the static equilibria there and keeps their difference
delta_j from the linear responses, a *defect correction* added to the reduced model's
displacements, ``Q y(theta) + delta_j``; until the minimiser stops moving. delta changes slowly
with theta, so a few rounds (one linear and one warm-started static solve per load case each)
reach the minimiser of the nonlinear cost, where a derivative-free polish on static solves
would need a hundred (:func:`fit_reduced`).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import numpy as np
from scipy.optimize import minimize

from ..dynamics.equilibrium import Equilibrium, StaticSolver
from ..model.forces import Stiffness
from ..model.stiffness import model_stiffness
from .cost import StaticCost
from .reduced import ReducedBasis, ReducedLinearModel

CONVERGED = 2e-3
"""The fit has converged when no parameter moved more than this (relative) in a round."""
FIRST_STEP = 0.2
"""The first reduced fit's Nelder-Mead simplex, log units (later ones: twice the last move)."""
MAX_EVALUATIONS = 400
"""Nelder-Mead evaluations of the reduced cost per round."""

DEFECT_ROUNDS = 8
"""At most this many rounds: a reduced fit, then a full linear and a static solve per load case
at its minimiser (the basis grows, the defect is renewed)."""


CASE_SOLVERS = 2
"""A round of :func:`fit_reduced` splits its solves over this many static solvers, each
solving its share one after the other on a thread of its own: solver 0 (the cost's) every
load case's full linear response (a CG from the reduced model's answer: after the first round
a tenth of a static solve) and case 0's static equilibrium, the others the other cases'
static equilibria in turn. The answer does not depend on the threads (a solver's solves
always run in the same order); each more solver holds one more multigrid hierarchy and tangent
buffer."""


def fit_reduced(
    cost: StaticCost,
    basis: ReducedBasis,
    start: list[float],
    bounds: tuple[np.ndarray, np.ndarray],
    progress: Callable[[dict[str, Any]], None] | None = None,
    threads: int = CASE_SOLVERS,
    after_round: Callable[[int], None] | None = None,
) -> tuple[list[float], float, int]:
    """Minimise Eq. (2) of the nonlinear static equilibria within ``bounds`` from ``start``:
    reduced linear fits on ``basis`` with enrichment, corrected by the nonlinear defect until
    the minimiser stops moving (this module's docstring).

    Each round's full linear and static solves are split over static solvers
    (:data:`CASE_SOLVERS`), the solvers' shares at once on ``threads`` threads with the same
    answer to the bit. The static equilibria at the answer are left as ``cost``'s
    warm starts, so a static solve there takes no Newton step. ``progress`` gets {phase:
    "polish", round, evaluations} after each round; ``after_round`` the round's number, after
    each round that goes on, while no solve runs (the damping stage starts the modes there:
    :class:`fpm.dynamics.modes_ahead.ModesAhead`).

    A round where a load case has no static equilibrium ends the fit at the round before (at
    ``start`` when it is the first).

    Returns (parameters, their normalised static cost (inf when the first round already had
    no equilibrium), the full linear solves it made)."""
    problem = cost.problem
    model = ReducedLinearModel.of(problem, basis, cost.reference)
    n_cases = len(model.cases)
    solvers = [cost.solver] + [StaticSolver(problem) for _ in range(1, min(CASE_SOLVERS, n_cases))]
    # whose static equilibrium each solver finds (solver 0 also every linear response)
    others = len(solvers) - 1
    statics = [0 if j == 0 or not others else 1 + (j - 1) % others for j in range(n_cases)]
    model.attach([solvers[0]] * n_cases, cost.depth)
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    y = np.clip(np.log(np.asarray(start, dtype=float)), lo, hi)
    static = float("inf")
    step = FIRST_STEP
    solved: list[Equilibrium] = []
    kept: tuple[np.ndarray, float, Stiffness | None, list[Equilibrium]] = (y, static, None, [])
    with ThreadPoolExecutor(threads, thread_name_prefix="reduced") as pool:
        for rounds in range(1, DEFECT_ROUNDS + 1):
            previous = y
            y = _reduced_minimum(model, y, lo, hi, step)
            step = max(min(step, 2 * float(np.abs(y - previous).max())), 10 * CONVERGED)
            theta = np.exp(y)
            stiffness = model_stiffness(problem, theta)
            responses = model.responses(theta)
            tasks = [
                partial(_solver_round, list(enumerate(responses)) if g == 0 else [],
                        [j for j in range(n_cases) if statics[j] == g], solver, stiffness,
                        cost.depth)
                for g, solver in enumerate(solvers)
            ]  # fmt: skip
            linear: dict[int, np.ndarray] = {}
            equilibria: dict[int, Equilibrium] = {}
            for found, solved_here in pool.map(lambda run: run(), tasks):
                linear.update(found)
                equilibria.update(solved_here)
            model.add(linear[j] for j in range(n_cases))  # the basis grows
            solved = [equilibria[j] for j in range(n_cases)]
            if not all(e.converged for e in solved):
                # No equilibrium there: the reduced model led where the solid has none (a
                # lattice that shears freely under a stiff volume term, say). The answer is
                # the last round that had one, or the start.
                y, static, kept_stiffness, solved = kept
                if kept_stiffness is not None:  # else solved is empty: nothing to seed
                    stiffness = kept_stiffness
                break
            cost.evaluations += 1
            static = sum(cost.case_cost(j, e.displacements) for j, e in enumerate(solved))
            static /= cost.reference_cost
            kept = (y, static, stiffness, solved)
            for case, equilibrium in zip(model.cases, solved, strict=True):
                assert case.last is not None
                defect = equilibrium.displacements[case.free] - case.last.reshape(-1, 3)
                case.set_correction(defect)
            if progress is not None:
                progress({"phase": "polish", "round": rounds, "evaluations": cost.evaluations})
            if float(np.abs(y - previous).max()) < CONVERGED:
                break
            if after_round is not None:
                after_round(rounds)
    for j, equilibrium in enumerate(solved):  # the other solvers' answers as cost's warm starts
        if statics[j] and equilibrium.converged:
            cost.solver.seed(j, stiffness, cost.depth, equilibrium.displacements)
    return list(np.exp(y)), static, model.solves


def _solver_round(
    responses: list[tuple[int, Callable[[], np.ndarray]]],
    statics: list[int],
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int | None,
) -> tuple[dict[int, np.ndarray], dict[int, Equilibrium]]:
    """One solver's share of a round of :func:`fit_reduced`, one solve after the other: the
    full linear responses of ``responses`` (load case j, the call from
    :meth:`ReducedLinearModel.responses`, which solves on this solver), then the static
    equilibria of load cases ``statics`` at ``stiffness`` on ``solver``. Returns ({j: response
    (3M,)}, {j: equilibrium})."""
    linear = {j: response() for j, response in responses}
    return linear, {j: solver.solve(j, stiffness, depth) for j in statics}


def _reduced_minimum(
    model: ReducedLinearModel, y: np.ndarray, lo: np.ndarray, hi: np.ndarray, step: float
) -> np.ndarray:
    """log theta minimising the (corrected) reduced cost, Nelder-Mead from ``y`` with an initial
    simplex of ``step`` (log units) along each parameter."""

    def f(z: np.ndarray) -> float:
        return model(np.exp(np.clip(z, lo, hi)))

    value = f(y)
    simplex = np.vstack([y] + [y + step * row for row in np.eye(len(y))])
    r = minimize(
        f,
        y,
        method="Nelder-Mead",
        bounds=list(zip(lo, hi, strict=True)),
        options={
            "xatol": 0.1 * CONVERGED,
            "fatol": 1e-7 * value,
            "maxfev": MAX_EVALUATIONS,
            "initial_simplex": np.clip(simplex, lo, hi),
        },
    )
    return np.asarray(r.x)
