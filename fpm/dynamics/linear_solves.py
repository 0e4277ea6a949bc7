"""The static solver's linear solves (:class:`fpm.dynamics.equilibrium.StaticSolver`):
tangent x = rhs over a perturbed list's free nodes.

Sparse LU below :data:`AMG_FROM_UNKNOWNS` unknowns; above, conjugate gradients preconditioned
by a smoothed-aggregation multigrid hierarchy (the FEM's hierarchy, V-cycle and CG, from
:mod:`fpm.fem.linear_solver`) built on one tangent and kept across Newton steps, stiffness
changes, load cases and calls for as long as CG converges at the rate it had when the hierarchy
was new (:class:`LinearSolves`: the Newton steps' solves, the list's hierarchy, the linear
response at rest and the solves of a given tangent, e.g. an adjoint's).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from ..fem.linear_solver import (
    ReusedHierarchy,
    SingularStiffnessError,
    amg_hierarchy,
    conjugate_gradients,
    factorize,
    rigid_body_modes,
)
from ..model.forces import Stiffness
from ..model.problem import Problem
from .spring_system import Params, SpringSystem

AMG_FROM_UNKNOWNS = 300
"""Free unknowns from which the Newton steps use multigrid-preconditioned CG instead of LU: from
about here CG is the faster, and SuperLU's fill-in on the 27-point stencil grows fast with size;
below, LU is as fast and copes with singular tangents (the timings:
docs/notes/2026-11-28-calibration-measured.md, *Thresholds*)."""

MAX_CG_ITERATIONS = 300
"""CG iterations per Newton step; a step that needs more uses what CG reached (still a descent
direction) and the hierarchy is rebuilt for the next."""

SHIFT = 1e-8
"""Diagonal shift, relative to the largest diagonal entry, of the last-resort tangent (a
singular one: a mechanism)."""

_MULTIGRID_SETUP = threading.Lock()
"""One multigrid setup at a time in a process: the solvers of chains running at once on threads
would otherwise hold two setups' transients together (a tangent and smoothed aggregation's
intermediates), the peak of the calibration's memory."""


class LinearSolves:
    """The linear solves of a :class:`~fpm.dynamics.equilibrium.StaticSolver` (one of its
    bases), with the multigrid hierarchies it keeps per list: what they read of the solver is
    declared here, set by its constructor."""

    problem: Problem
    amg_from: int
    hierarchies_built: int
    _multigrid: dict[bytes, ReusedHierarchy]
    system: Callable[[int, int | None], tuple[SpringSystem, int]]

    def _linear_solve(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        tangent: sp.bsr_matrix,
        rhs: np.ndarray,
        eta: float,
        nodal_stop: float,
    ) -> tuple[np.ndarray, int]:
        """Solve tangent x = rhs: by LU (exactly) for small systems, else by CG preconditioned
        by the list's multigrid hierarchy (built on the clamped tangent at u when missing or
        stale) to the relative residual eta or the nodal residual ``nodal_stop``, N.
        Returns x and the CG iterations (0 for LU).

        Raises:
            NegativeCurvature: CG found ``tangent`` is not positive definite.
            SingularStiffnessError: LU found it singular.
        """
        if 3 * system.n_free < self.amg_from:
            return _direct_solve(tangent, rhs), 0
        mg = self._hierarchy(system, u, k)
        cg = conjugate_gradients(
            tangent,
            rhs,
            mg.precondition,
            rtol=eta,
            max_iterations=MAX_CG_ITERATIONS,
            nodal_stop=nodal_stop,
        )
        mg.record(cg.iterations, cg.residual, cg.converged)
        return cg.x, cg.iterations

    def multigrid(self, system: SpringSystem) -> ReusedHierarchy | None:
        """The multigrid hierarchy this solver keeps for ``system``'s list (None: none yet)."""
        return self._multigrid.get(system.free.tobytes())

    def _linear_hierarchy(
        self, system: SpringSystem, tangent: sp.sparray | sp.spmatrix
    ) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on ``tangent`` when there is none."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None:
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                blocks = sp.bsr_matrix(tangent, blocksize=(3, 3))
                mg = ReusedHierarchy(amg_hierarchy(blocks, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def _hierarchy(self, system: SpringSystem, u: np.ndarray, k: Params) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on the clamped tangent at u when missing or
        stale."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None or mg.stale:
            self._multigrid.pop(key, None)  # the stale one goes before the new one is built
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                reference = system.tangent(u, k, modified=True, shift=SHIFT * 1e-3)
                mg = ReusedHierarchy(amg_hierarchy(reference, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def linear_response(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m, of ``load_case``'s list linearised at rest (each spring
        acting along its rest direction) under nodal ``loads`` (N, 3), N; zero off the list.

        Solved to a relative residual of ``rtol`` (LU or multigrid CG as for Newton steps; the
        solve does not count towards the hierarchy's staleness); CG starts from ``guess``
        ((N, 3), m; e.g. a reduced model's answer) when given.

        Raises:
            SingularStiffnessError, NegativeCurvature: the linear lattice is not held (e.g. an
                'axis' lattice at rest is a mechanism).
        """
        system, _ = self.system(load_case, depth)
        k = system.parameters(Stiffness.of(stiffness))
        tangent = system.tangent(np.zeros((system.n_free, 3)), k, modified=True)
        return self.linear_solve(load_case, depth, tangent, loads, guess=guess, rtol=rtol)

    def linear_solve(
        self,
        load_case: int,
        depth: int | None,
        tangent: sp.sparray | sp.spmatrix,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m: ``tangent`` (3M, 3M) (a stiffness over the list's free
        nodes, e.g. :meth:`SpringSystem.tangent` at rest) solved for nodal ``loads`` (N, 3), N,
        as :meth:`linear_response` does; zero off the list. ``rtol`` >= 1 asks for one
        multigrid V-cycle only (LU is exact below AMG_FROM_UNKNOWNS)."""
        system, _ = self.system(load_case, depth)
        rhs = np.ascontiguousarray(loads[system.free]).ravel()
        if 3 * system.n_free < self.amg_from:
            x = _direct_solve(tangent, rhs)
        elif rtol >= 1.0:  # one multigrid V-cycle: an approximate answer, for search directions
            x = self._linear_hierarchy(system, tangent).precondition(rhs)
        else:
            start = np.zeros_like(rhs)
            if guess is not None:
                start = np.ascontiguousarray(guess[system.free]).ravel()
            left = rhs - tangent @ start
            size, remaining = float(np.linalg.norm(rhs)), float(np.linalg.norm(left))
            x = start
            if remaining > rtol * size:
                mg = self._linear_hierarchy(system, tangent)
                cg = conjugate_gradients(
                    tangent, left, mg.precondition, rtol=rtol * size / remaining,
                    max_iterations=10 * MAX_CG_ITERATIONS,
                )  # fmt: skip
                x = start + cg.x
        out = np.zeros_like(self.problem.nodes)
        out[system.free] = x.reshape(-1, 3)
        return out


def _direct_solve(tangent: sp.bsr_matrix, rhs: np.ndarray) -> np.ndarray:
    """Sparse LU solve (:func:`fpm.fem.linear_solver.factorize`).

    Raises:
        SingularStiffnessError: the tangent is singular, or the solve is not finite.
    """
    x = factorize(tangent.tocsc(), "direct", np.zeros((0, 6)))(rhs)
    if not np.all(np.isfinite(x)):
        raise SingularStiffnessError("the LU solve is not finite")
    return np.asarray(x)
