"""The static solver's Newton iteration (:class:`fpm.dynamics.equilibrium.StaticSolver`):
from where it starts to the equilibrium.

Each Newton step tries the exact tangent first (quadratic convergence); where it is not positive
definite (CG meets negative curvature, or the step does not descend) the step is redone with the
factor (1 - L/|r|) clamped at 0, a positive semi-definite tangent whose steps always descend; where
that is singular (a mechanism), with a small diagonal shift. A backtracking (Armijo) line search on
E makes every step decrease it (energy changes are computed without cancellation:
:meth:`~fpm.dynamics.spring_system.SpringSystem.energy_change`). Inexact Newton: CG stops at a
residual relative to the current one (Eisenstat-Walker, choice 2), or once every node's linear
residual is below half the target. Newton starts from rest or from the warm starts' prediction
refined on a Galerkin reduced model (:mod:`fpm.dynamics.predictor`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.problem import Problem
from .linear_solves import SHIFT
from .predictor import ARMIJO, _galerkin, _largest, _Predictor, _Stats
from .spring_system import Params, SpringSystem

MAX_ITERATIONS = 100
"""Newton iterations before a solve gives up."""

ETA_MAX = 0.1
"""Largest relative CG tolerance of an inexact Newton step (Eisenstat-Walker's eta)."""

NEAR = 1e3
"""Within this factor of the target residual, a Newton step's CG runs to the target (the
quadratic term is negligible there, so one accurate step beats two loose ones)."""

DIVERGED = 10.0
"""A Newton iterate that moves a node this many times the solid's size away has diverged. An
equilibrium further than the size itself is reported as not converged (a dynamic run stops
there as diverged)."""


class Newton:
    """The Newton iteration of a :class:`~fpm.dynamics.equilibrium.StaticSolver` (one of its
    bases; the linear solves are :class:`~fpm.dynamics.linear_solves.LinearSolves`'): what it
    reads of the solver is declared here, set by its constructor."""

    problem: Problem
    warm: bool
    _buffers: dict[bytes, np.ndarray]
    _linear_solve: Callable[..., tuple[np.ndarray, int]]

    def _start(
        self,
        predictor: _Predictor,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        applied: float,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Where Newton starts, and dE/du there: rest, or the predictor's guess refined on the
        reduced model."""
        rest = np.zeros((system.n_free, 3))
        if not self.warm or not predictor.snapshots or not len(k.flat):
            return rest, -forces
        scale, spread = predictor.relation(k.flat)
        u = predictor.predict(system.n_free, scale, spread)
        gradient = system.gradient(u, k, forces)
        if not _largest(gradient) < applied:  # worse than rest (the residual at rest: forces)
            return rest, -forces
        stats.start = "predicted"
        if _largest(gradient) > target:
            basis = predictor.basis(scale, spread)
            if basis is not None:
                u, gradient = _galerkin(system, k, forces, u, gradient, basis, target)
        return u, gradient

    def _newton(
        self,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        u: np.ndarray,
        gradient: np.ndarray,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, float, bool]:
        """Newton with an Armijo line search on E from ``u`` (``gradient`` = dE/du there);
        returns (u, residual, converged)."""
        limit = self.problem.size
        residual = _largest(gradient)
        if residual <= target:
            return u, residual, self._within_size(u, stats)
        eta = ETA_MAX
        previous_norm: float | None = None
        for iteration in range(1, MAX_ITERATIONS + 1):
            stats.iterations = iteration
            norm = float(np.sqrt(np.einsum("ij,ij->", gradient, gradient)))
            if previous_norm is not None:  # Eisenstat-Walker choice 2, safeguarded
                ew = 0.9 * (norm / previous_norm) ** 2
                if 0.9 * eta * eta > 0.1:
                    ew = max(ew, 0.9 * eta * eta)
                eta = min(ETA_MAX, ew)
            if residual <= NEAR * target:  # close: the quadratic term is negligible
                eta = 0.0
            eta = max(eta, 0.5 * target / norm)  # no need to solve past the tolerance
            previous_norm = norm
            step, slope = self._newton_step(system, u, k, gradient, eta, 0.5 * target, stats)
            if step is None:
                stats.message = "the Newton step is not a descent direction (singular tangent?)"
                return u, residual, False
            alpha = 1.0
            for _ in range(40):
                change = system.energy_change(u, alpha * step, k, forces)
                if change <= ARMIJO * alpha * slope:
                    break
                # At round-off level (|slope| tiny against the forces' work) accept a step that
                # lowers the residual instead.
                work = abs(float(np.einsum("ij,ij->", forces, step)))
                if abs(slope) < 1e-11 * work:
                    trial = system.gradient(u + alpha * step, k, forces)
                    if _largest(trial) < residual:
                        break
                # Backtrack: minimiser of the quadratic through E(0), E'(0) and E(alpha).
                quad = -slope * alpha * alpha / (2.0 * (change - slope * alpha))
                alpha = min(max(quad, 0.1 * alpha), 0.5 * alpha) if np.isfinite(quad) else alpha / 2
            else:
                stats.message = f"line search failed at Newton iteration {iteration}"
                return u, residual, False
            u = u + alpha * step
            gradient = system.gradient(u, k, forces)
            residual = _largest(gradient)
            if not np.isfinite(residual) or not np.all(np.isfinite(u)):
                stats.message = "diverged: the state became non-finite"
                return u, float("inf"), False
            if _largest(u) > DIVERGED * limit:
                stats.message = f"diverged: a node moved {DIVERGED:g} x the solid's size away"
                return u, residual, False
            if residual <= target:
                return u, residual, self._within_size(u, stats)
        stats.message = (
            f"no convergence in {MAX_ITERATIONS} Newton iterations "
            f"(residual {residual:.3g} N, target {target:.3g} N)"
        )
        return u, residual, False

    def _within_size(self, u: np.ndarray, stats: _Stats) -> bool:
        """An equilibrium moving a node further than the solid's size is what a dynamic run
        stops at as diverged: not converged."""
        limit = self.problem.size
        if _largest(u) > limit:
            stats.message = (
                f"the equilibrium moves a node further than the solid's size, {limit:g} m"
            )
            return False
        return True

    def _newton_step(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        gradient: np.ndarray,
        eta: float,
        nodal_stop: float,
        stats: _Stats,
    ) -> tuple[np.ndarray | None, float]:
        """The Newton step (M, 3) and its slope gradient . step (< 0), or (None, nan).

        The exact tangent first (quadratic convergence near the solution); where it is not
        positive definite (compressed springs) the clamped one, whose steps always descend;
        where that is singular (a mechanism, e.g. an `axis` lattice at rest) the clamped one
        with a small diagonal shift (Levenberg-Marquardt).
        """
        key = system.free.tobytes()
        buffer = self._buffers.get(key)
        if buffer is None:
            buffer = self._buffers[key] = system.blocks()
        for modified, shift in ((False, 0.0), (True, 0.0), (True, SHIFT)):
            tangent = system.tangent(u, k, modified=modified, shift=shift, out=buffer)
            try:
                x = self._linear_solve(system, u, k, tangent, -gradient.ravel(), eta, nodal_stop)
            except NegativeCurvature as e:
                stats.linear_iterations += e.args[0]
                continue
            except SingularStiffnessError:
                continue
            stats.linear_iterations += x[1]
            step = x[0].reshape(-1, 3)
            slope = float(np.einsum("ij,ij->", gradient, step))
            if slope < 0:
                return step, slope
        return None, float("nan")
