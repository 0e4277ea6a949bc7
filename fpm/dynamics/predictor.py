"""Warm starts of the static solver: where Newton starts from, given the solutions it found
before.

Converged solutions are kept per (load case, depth) (:class:`_Predictor`, at most
:data:`SNAPSHOTS`), each as the free nodes' displacements u (M, 3), m, with its springs'
stiffness, N/m, at a fixed sample of springs. With one k, u(c k, F) = u(k, F / c) exactly, so
solutions at proportional stiffnesses are interpolated along the load factor; otherwise the
nearest is rescaled; then E is minimised over the span of the nearest few (a Galerkin reduced
model, :func:`_galerkin`: chord-Newton steps on the m x m reduced tangent Q^T K Q, N/m, with
an orthonormal basis Q (M, 3, m), m <= :data:`GALERKIN_SIZE`). On an annealing walk with one k
most solves then need no Newton step at all. A start is only a start: the static solver
(:mod:`fpm.dynamics.equilibrium`) checks every answer against the full residual.

Also here, as the reduced model's line search and counters are those of Newton's: the
sufficient-decrease constant :data:`ARMIJO`, a solve's counters (:class:`_Stats`) and the
residual measure :func:`_largest` (the largest nodal force, N, of a gradient (M, 3)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..fem.linear_solver import dot
from .spring_system import Params, SpringSystem

ARMIJO = 1e-4
"""Sufficient-decrease constant of the line searches (Newton's and the reduced model's):
accept E(u + a p) - E(u) <= ARMIJO a g.p."""

SNAPSHOTS = 12
"""Converged solutions kept per (load case, depth) for warm starts."""

LAGRANGE_POINTS = 4
"""Solutions at proportional stiffnesses interpolated along the load factor (with s = 0)."""

SAMPLE = 4096
"""Springs (evenly spread) on which a warm start compares stiffnesses."""

GALERKIN_SIZE = 8
"""Nearest solutions spanning the reduced model a warm start is refined on."""

GALERKIN_ITERATIONS = 4
"""Chord-Newton steps on the reduced model (:func:`_galerkin`)."""


@dataclass
class _Snapshot:
    """A converged solution: free displacements u (M, 3), m, and its active springs'
    stiffness at the :data:`SAMPLE` of springs, N/m (the whole (A,) array would cost more
    memory than u)."""

    u: np.ndarray
    k_sample: np.ndarray


class _Predictor:
    """Starting points for one (load case, depth) from its earlier solutions (warm starts).

    Let k be the new stiffness and u_j an earlier solution found at stiffness c_j k
    (proportional, as when one k changes). The equilibrium equations are homogeneous in
    (k, F), so u_j = u(k, F / c_j): u_j is the point s_j = 1 / c_j of the curve
    w(s) = u(k, s F), which also passes through w(0) = 0, and the answer is w(1). So solutions
    at proportional stiffnesses are interpolated along s (Lagrange, through 0 and the nearest
    few); with a single one that is the rescaling c_j u_j, exact for the linear part. Otherwise
    (family stiffnesses changed unevenly) the nearest solution, rescaled by its mean stiffness
    ratio. Then, with two or more solutions kept, E is minimised over their span (a Galerkin
    reduced model, :func:`_galerkin`), which captures how the answer varies with the stiffness
    from the solutions already found.

    Stiffnesses are compared on a fixed sample of springs (:data:`SAMPLE`): a mismatch outside
    it only makes a start worse, never an answer wrong (every answer is checked against the
    residual).
    """

    def __init__(self, n_springs: int) -> None:
        self.snapshots: list[_Snapshot] = []
        self.sample = slice(None, None, max(1, n_springs // SAMPLE))

    def add(self, u: np.ndarray, k: np.ndarray) -> None:
        """Keep a converged solution (replacing one at the same stiffness; oldest out)."""
        sample = k[self.sample].copy()
        self.snapshots = [s for s in self.snapshots if not np.array_equal(s.k_sample, sample)]
        self.snapshots.append(_Snapshot(u.copy(), sample))
        del self.snapshots[:-SNAPSHOTS]

    def relation(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per snapshot: log c_j (its stiffness over k, geometric mean over the sample) and
        the spread of the log ratio about it (0: proportional)."""
        logs = np.log(np.stack([s.k_sample for s in self.snapshots])) - np.log(k[self.sample])
        scale = logs.mean(axis=1)
        spread = np.sqrt(((logs - scale[:, None]) ** 2).mean(axis=1))
        return scale, spread

    def predict(self, n_free: int, scale: np.ndarray, spread: np.ndarray) -> np.ndarray:
        """Starting displacements (M, 3) before the reduced-model refinement."""
        if not self.snapshots:
            return np.zeros((n_free, 3))
        proportional = np.flatnonzero(spread < 1e-12)
        if len(proportional):
            nearest: list[int] = []  # distinct nodes only (close ones make wild weights)
            for j in proportional[np.argsort(np.abs(scale[proportional]))]:
                if all(abs(scale[j] - scale[i]) > 1e-6 for i in nearest):
                    nearest.append(int(j))
            nearest = nearest[:LAGRANGE_POINTS]
            nodes = np.concatenate([[0.0], np.exp(-scale[nearest])])  # s_j = 1 / c_j
            u = np.zeros((n_free, 3))
            for a, j in enumerate(nearest, start=1):
                others = np.delete(nodes, a)
                u += float(np.prod((1.0 - others) / (nodes[a] - others))) * self.snapshots[j].u
            return u
        best = int(np.argmin(np.hypot(scale, spread)))
        return self.snapshots[best].u * math.exp(scale[best])

    def basis(self, scale: np.ndarray, spread: np.ndarray) -> np.ndarray | None:
        """(M, 3, m) orthonormal basis of the span of the nearest (<= GALERKIN_SIZE)
        solutions, or None with fewer than two."""
        if len(self.snapshots) < 2:
            return None
        columns: list[np.ndarray] = []
        for j in np.argsort(np.hypot(scale, spread))[:GALERKIN_SIZE]:
            v = self.snapshots[j].u.ravel().copy()  # modified Gram-Schmidt, twice (no BLAS)
            size = math.sqrt(dot(v, v))
            for _ in range(2):
                for q in columns:
                    v -= dot(q, v) * q
            left = math.sqrt(dot(v, v))
            if left > 1e-8 * size:
                columns.append(v / left)
        if len(columns) < 2:
            return None
        return np.stack(columns, axis=1).reshape(-1, 3, len(columns))


@dataclass
class _Stats:
    """What one static solve did: Newton and CG iterations, why it stopped (``message``) and
    where it started (``start``: "rest" or "predicted")."""

    iterations: int = 0
    linear_iterations: int = 0
    message: str = ""
    start: str = "rest"


def _galerkin(
    system: SpringSystem,
    k: Params,
    forces: np.ndarray,
    u: np.ndarray,
    gradient: np.ndarray,
    basis: np.ndarray,
    target: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise E over u + span(basis) (basis (M, 3, m) orthonormal): chord-Newton steps on
    the m x m reduced tangent Q^T K Q at the start (exact; clamped where the exact one is not
    positive definite), each with an Armijo line search on E. One reduced tangent per solve,
    O(A m^2).
    """
    m = basis.shape[2]
    q = basis.reshape(-1, m)
    for modified in (False, True):
        hessian = system.reduced_tangent(u, k, basis, modified)
        if np.all(np.isfinite(hessian)) and np.linalg.eigvalsh(hessian).min() > 0:
            break
    else:
        return u, gradient
    first = None
    for _ in range(GALERKIN_ITERATIONS):
        reduced = np.einsum("ia,i->a", q, gradient.ravel())
        size = float(np.linalg.norm(reduced))
        first = size if first is None else first
        if size <= 1e-6 * first:
            break
        coefficients = -np.linalg.solve(hessian, reduced)
        step = np.einsum("ia,a->i", q, coefficients).reshape(-1, 3)
        slope = float(np.dot(reduced, coefficients))
        if not slope < 0:
            break
        alpha = 1.0
        for _ in range(8):
            if system.energy_change(u, alpha * step, k, forces) <= ARMIJO * alpha * slope:
                break
            alpha *= 0.5
        else:
            break
        u = u + alpha * step
        gradient = system.gradient(u, k, forces)
        if _largest(gradient) <= target:
            break
    return u, gradient


def _largest(vectors: np.ndarray) -> float:
    """Largest Euclidean norm of the rows of ``vectors`` (M, 3)."""
    if not len(vectors):
        return 0.0
    return float(np.sqrt(np.einsum("ij,ij->i", vectors, vectors).max()))
