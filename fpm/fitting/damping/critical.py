"""Critical-damping estimates (:func:`critical_damping`): where the d search starts when the
lattice's slowest modes predict nothing (:mod:`fpm.fitting.damping.search`, its module
docstring): two shapes that bracket the slow motion a load excites, the static deflection and
the deflection under its own inertia (:func:`damping_guesses`)."""

from __future__ import annotations

import math

import numpy as np

from ...dynamics.equilibrium import StaticSolver
from ...fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ...model.forces import Stiffness
from ...model.problem import Problem


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
    """Two critical-damping estimates, N s/m (:func:`critical_damping`): from the static shapes
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
