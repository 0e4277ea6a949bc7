"""The stiffness field's fit by gradients (:mod:`fpm.fitting.field`): Eq. (2) over load
cases, its gradient by the adjoint, and L-BFGS-B on it.

At an equilibrium, g(u, k) = dE/du = 0 over the list's free nodes. For a cost J(u), dJ/dk =
-lambda . dg/dk with H lambda = dJ/du, H = dg/du the exact tangent
(:meth:`fpm.dynamics.equilibrium.StaticSolver.linear_solve`): one linear solve per load case,
whatever the number of parameters (:func:`case_gradient`). Per spring lambda . dg/dk_s =
(|r_s| - L_s) n_s . (lambda_j - lambda_i), per cell lambda . dg/dkappa_c = (V_c - V0_c) /
V0_c sum_n g_n . lambda_n (:meth:`fpm.dynamics.spring_system.SpringSystem.sensitivity`), then
through the cells' shares to the factors (:class:`fpm.fitting.field_parameters.FieldMap`).
tests/core/test_field.py checks it against central differences.

The normalised cost of the fitted load cases j over all nodes i (p the FPM's equilibrium, q
the reference) plus the weighted smoothness penalty P(x),

    f(x) = sum_j sum_i |p_ij(x) - q_ij| / sum_j sum_i |q_ij|  +  w P(x),

is L-BFGS-B's objective (:class:`Objective`, :func:`minimise`); within an evaluation the load
cases run on threads, each with its own static solver (:class:`Solvers`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import minimize

from ..dynamics.equilibrium import StaticSolver
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.forces import Stiffness
from .field_parameters import Parameters

ADJOINT_RTOL = 1e-2
"""Relative residual of the adjoint solves in a fit (multigrid CG; exact LU on small lists):
the gradient to about this, enough for L-BFGS-B."""
FIT_TOLERANCE = 1e-6
"""The static equilibria in a fit are solved to this (largest unbalanced nodal force over the
largest applied one; the reported figures to the solver's default, a tenth of the settle
tolerance)."""
FAILED = 1e3
"""The normalised cost reported where a load case has no equilibrium (L-BFGS-B backtracks)."""


class FieldError(RuntimeError):
    """A load case without a static equilibrium where the field fit needs one."""


@dataclass
class CaseGradient:
    """One load case's Eq. (2) cost at an equilibrium and its adjoint gradient.

    Attributes:
        cost: sum_i |p_i - q_i| over every node, m.
        springs: (S,) dcost/dk_s, m / (N/m).
        kappa: (H,) dcost/dkappa_c, m / Pa (zeros without a volume term).
        displacements: (N, 3) the equilibrium, m.
        adjoint: (N, 3) lambda, the tangent's solution for dcost/du, m/N.
    """

    cost: float
    springs: np.ndarray
    kappa: np.ndarray
    displacements: np.ndarray
    adjoint: np.ndarray


def case_gradient(
    solver: StaticSolver,
    load_case: int,
    reference: np.ndarray,
    stiffness: Stiffness,
    depth: int | None,
    *,
    tolerance: float | None = None,
    rtol: float = ADJOINT_RTOL,
    guess: np.ndarray | None = None,
) -> CaseGradient:
    """The cost of ``load_case``'s static equilibrium at ``stiffness`` against ``reference``
    (N, 3), m, and its gradient by the stiffness of every spring and cell (this module's
    docstring: one adjoint solve with the exact tangent, CG starting from ``guess`` (N, 3),
    e.g. the last adjoint of the load case; the result's ``adjoint``).

    Raises:
        FieldError: the load case has no static equilibrium there.
    """
    problem = solver.problem
    eq = solver.solve(load_case, stiffness, depth, tolerance=tolerance)
    if not eq.converged:
        raise FieldError(f"load case {problem.load_cases[load_case].name!r}: {eq.message}")
    error = eq.displacements - reference
    size = np.sqrt(np.einsum("ij,ij->i", error, error))
    system, _ = solver.system(load_case, depth)
    pull = np.zeros_like(error)  # dcost/du on the free nodes (the others do not move)
    free = system.free[size[system.free] > 0]
    pull[free] = error[free] / size[free, None]
    u = eq.displacements[system.free]
    k = system.parameters(stiffness)
    tangent = system.tangent(u, k, modified=False)
    try:
        adjoint = solver.linear_solve(load_case, depth, tangent, pull, guess=guess, rtol=rtol)
    except (NegativeCurvature, SingularStiffnessError):  # rare: LU on the exact tangent
        adjoint = np.zeros_like(pull)
        rhs = np.ascontiguousarray(pull[system.free]).ravel()
        adjoint[system.free] = sp.linalg.spsolve(tangent.tocsc(), rhs).reshape(-1, 3)
    spring_part, cell_part = system.sensitivity(u, adjoint[system.free])
    springs = np.zeros(len(stiffness.springs))
    springs[system.springs] = -spring_part
    kappa = np.zeros(0 if stiffness.volume is None else len(stiffness.volume))
    if len(kappa):
        kappa[system.cell_ids] = -cell_part
    return CaseGradient(float(size.sum()), springs, kappa, eq.displacements, adjoint)


class Solvers:
    """A static solver per load case (``solvers[j]`` serves load case j; one solver may serve
    several, serially) and the threads an evaluation's load cases run on. Each solver keeps
    its load case's warm starts and multigrid hierarchy, so an answer does not depend on the
    number of threads (:class:`~fpm.dynamics.equilibrium.StaticSolver` is not thread-safe:
    give distinct solvers when ``threads`` > 1)."""

    def __init__(self, solvers: Sequence[StaticSolver], threads: int = 1):
        self.solvers = list(solvers)
        if threads > 1 and len({id(s) for s in self.solvers}) < len(self.solvers):
            raise ValueError("load cases on threads need a solver each")
        self.pool = ThreadPoolExecutor(threads) if threads > 1 else None

    def __getitem__(self, load_case: int) -> StaticSolver:
        return self.solvers[load_case]

    def map(self, work: Callable[[int], Any], cases: Sequence[int]) -> list[Any]:
        """``[work(j) for j in cases]``, on the threads."""
        if self.pool is None:
            return [work(j) for j in cases]
        return list(self.pool.map(work, cases))

    def relative(
        self, reference: np.ndarray, cases: Sequence[int], stiffness: Stiffness, depth: int | None
    ) -> list[float]:
        """:func:`relative` of each of ``cases``, each by its own solver."""
        return self.map(lambda j: relative(self[j], reference, [j], stiffness, depth)[0], cases)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()


class Objective:
    """f(x) = Eq. (2) over ``cases`` / their reference cost + weight * smoothness, and its
    gradient (L-BFGS-B's fun with jac=True; the load cases on ``solvers``' threads, summed in
    case order); counts evaluations."""

    def __init__(
        self,
        solvers: Solvers,
        reference: np.ndarray,
        cases: Sequence[int],
        depth: int | None,
        parameters: Parameters,
        weight: float = 0.0,
        tolerance: float | None = FIT_TOLERANCE,
    ):
        self.solvers, self.reference, self.cases = solvers, reference, list(cases)
        self.depth, self.parameters, self.weight = depth, parameters, weight
        self.tolerance = tolerance
        self.scale = float(sum(np.linalg.norm(reference[j], axis=1).sum() for j in self.cases))
        self.evaluations = 0
        self.adjoints: dict[int, np.ndarray] = {}  # the last adjoint per load case: CG's start

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.evaluations += 1
        stiffness = self.parameters.stiffness(x)
        smooth, smooth_grad = self.parameters.smoothness(x)

        def one(j: int) -> CaseGradient:
            return case_gradient(
                self.solvers[j], j, self.reference[j], stiffness, self.depth,
                tolerance=self.tolerance, guess=self.adjoints.get(j),
            )  # fmt: skip

        try:
            found = self.solvers.map(one, self.cases)
        except FieldError:
            return FAILED, self.weight * smooth_grad
        total = 0.0
        springs = np.zeros(len(stiffness.springs))
        kappa = np.zeros(0 if stiffness.volume is None else len(stiffness.volume))
        for j, g in zip(self.cases, found, strict=True):
            self.adjoints[j] = g.adjoint
            total += g.cost
            springs += g.springs
            kappa += g.kappa
        grad = self.parameters.pull_back(x, springs, kappa) / self.scale
        return total / self.scale + self.weight * smooth, grad + self.weight * smooth_grad


def minimise(objective: Objective, x: np.ndarray, iterations: int) -> tuple[np.ndarray, int]:
    """L-BFGS-B from x within the parameters' bounds; returns (x, iterations taken)."""
    r = minimize(
        objective,
        x,
        jac=True,
        method="L-BFGS-B",
        bounds=objective.parameters.bounds(),
        options={"maxiter": iterations, "maxfun": 2 * iterations, "ftol": 1e-9, "gtol": 1e-9},
    )
    return np.asarray(r.x), int(r.nit)


def relative(
    solver: StaticSolver, reference: np.ndarray, cases: Sequence[int], stiffness: Stiffness,
    depth: int | None,
) -> list[float]:  # fmt: skip
    """The relative discrepancy, %, of each of ``cases`` at its static equilibrium (nan where
    there is none)."""
    out = []
    for j in cases:
        eq = solver.solve(j, stiffness, depth)
        q = reference[j]
        if not eq.converged:
            out.append(float("nan"))
            continue
        error = np.linalg.norm(eq.displacements - q, axis=1).sum()
        out.append(float(100 * error / np.linalg.norm(q, axis=1).sum()))
    return out
