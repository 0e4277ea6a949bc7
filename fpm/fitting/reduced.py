"""families+volume, stage 1: the fit on a reduced linear model (docs/physics.md, *Calibration*).

Linearised at rest, the lattice's stiffness matrix is linear in the fitted parameters:
``K(theta) = sum_p theta_p K_p`` (K_p: the matrix of family p's assembled springs at k = 1, and
of the cells at kappa = 1). Its response to a load case's forces f, ``u(theta) = K(theta)^-1 f``,
lies close to the span of a few responses at other parameters, so on a basis Q of such
responses (per load case, orthonormal) the reduced model

    u(theta) ~ Q (sum_p theta_p Q^T K_p Q)^-1 Q^T f

costs an m x m solve (m <= a few tens) instead of a sparse solve with 10^4-10^5 unknowns, and the
Eq. (2) cost of the linear model can be evaluated hundreds of times.

The model is nonlinear (springs rotate, cells change volume), and a probe's load moves its node
a good fraction of h. Each round therefore (1) minimises
the reduced cost (Nelder-Mead in log theta from the last minimiser), (2) solves the full linear
model at the minimiser and adds that response to the basis, (3) solves the static equilibria
there and keeps their difference delta_j from the linear responses, a *defect correction* added
to the reduced model's displacements, ``Q y(theta) + delta_j``; until the minimiser stops moving.
delta changes slowly with theta, so a few rounds (one linear and one warm-started static solve
per load case each) reach the minimiser of the nonlinear cost, where a derivative-free polish
on static solves would need a hundred.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.optimize import minimize

from ..model.problem import Problem
from ..model.stiffness import linear_parts
from .cost import StaticCost

CONVERGED = 2e-3
"""The fit has converged when no parameter moved more than this (relative) in a round."""
FIRST_STEP = 0.2
"""The first reduced fit's Nelder-Mead simplex, log units (later ones: twice the last move)."""
RTOL = 1e-6
"""Relative residual of the full linear solves that enrich the basis."""
MAX_EVALUATIONS = 400
"""Nelder-Mead evaluations of the reduced cost per round."""


@dataclass
class _Case:
    """One load case's reduced model: basis (M, m) over its free nodes, K_p projected, f."""

    free: np.ndarray
    unit: UnitMatrices  # the K_p
    loads: np.ndarray  # (3M,)
    reference: np.ndarray  # (M, 3) reference displacements of the free nodes
    held: float  # sum of |reference| over the nodes that do not move in this list
    basis: np.ndarray  # (3M, m)
    projected: np.ndarray  # (P, m, m)
    rhs: np.ndarray  # (m,)
    correction: np.ndarray | None = None  # (M, 3) nonlinear minus linear displacements
    last: np.ndarray | None = None  # (3M,) the last full linear response added
    offset: np.ndarray | None = None  # (M, 3) correction minus reference (set by :meth:`cost`)

    def add(self, response: np.ndarray, *, last: bool = True) -> None:
        """Extend the basis by ``response`` (3M,) (Gram-Schmidt twice; dropped if dependent);
        ``last``: it is the full linear response at the parameters last enriched at."""
        if last:
            self.last = response
        v = response.copy()
        size = float(np.linalg.norm(v))
        for _ in range(2):
            if self.basis.shape[1]:
                v -= self.basis @ (self.basis.T @ v)
        left = float(np.linalg.norm(v))
        if size == 0 or left <= 1e-10 * size:
            return
        v /= left
        self.basis = np.column_stack([self.basis, v])
        kv = np.stack([self.unit.matrix(p) @ v for p in range(len(self.unit))])  # (P, 3M)
        column = np.einsum("ia,pi->pa", self.basis, kv)  # (P, m)
        m = self.basis.shape[1]
        projected = np.zeros((len(self.unit), m, m))
        projected[:, : m - 1, : m - 1] = self.projected
        projected[:, :, m - 1] = column
        projected[:, m - 1, :] = column
        self.projected = projected
        self.rhs = self.basis.T @ self.loads

    def linear(self, theta: np.ndarray) -> np.ndarray:
        """(3M,) the reduced linear model's displacements at theta."""
        a = np.einsum("p,pab->ab", theta, self.projected)
        return self.basis @ np.linalg.solve(a, self.rhs)

    def set_correction(self, correction: np.ndarray) -> None:
        """The defect correction (M, 3), m, added to the reduced displacements from now on."""
        self.correction = correction
        self.offset = None

    def cost(self, theta: np.ndarray) -> float:
        """Eq. (2) of the reduced linear model at theta, m (inf if it is not positive definite).

        One compiled pass over the basis (:func:`_reduced_cost`): the node's displacement
        from y, the correction, the distance to the reference, summed. Evaluated hundreds of
        times per round, it was 44% of a chain's time on the organ at h = 3 mm as NumPy
        (the matrix-vector product on a threaded BLAS and the temporaries of the norms)."""
        a = np.einsum("p,pab->ab", theta, self.projected)
        try:
            y = np.linalg.solve(a, self.rhs)
        except np.linalg.LinAlgError:
            return float("inf")
        if self.offset is None:
            base = -self.reference if self.correction is None else self.correction - self.reference
            self.offset = np.ascontiguousarray(base, dtype=float)
        return _reduced_cost(self.basis, y, self.offset) + self.held


@njit(cache=True, nogil=True)
def _reduced_cost(basis: np.ndarray, y: np.ndarray, offset: np.ndarray) -> float:
    """sum_i |(basis y)_i + offset_i|, m: ``basis`` (3M, m) node-major, ``y`` (m,),
    ``offset`` (M, 3) (correction minus reference), without forming basis y."""
    total = 0.0
    m = y.shape[0]
    for i in range(offset.shape[0]):
        s2 = 0.0
        for d in range(3):
            row = 3 * i + d
            v = offset[i, d]
            for a in range(m):
                v += basis[row, a] * y[a]
            s2 += v * v
        total += np.sqrt(s2)
    return total


SUM_PIECE = 1 << 16
"""Blocks per piece when K(theta) is summed (:meth:`UnitMatrices.at`): 4.7 MB of products."""


@dataclass(frozen=True)
class _Unit:
    """One K_p: its nonzero 3x3 blocks, where they sit in the list's block pattern, and their
    own pattern (``scipy.sparse.bsr_matrix``'s indices and indptr)."""

    values: np.ndarray  # (b, 3, 3)
    positions: np.ndarray  # (b,) indices into the list's blocks
    indices: np.ndarray
    indptr: np.ndarray


@dataclass(frozen=True)
class UnitMatrices:
    """The K_p of one perturbed list, (3M, 3M) N/m each (M the list's free nodes), each kept as
    its nonzero 3x3 blocks only (a family's springs touch 7, 13 or 9 of the 27 blocks of a row,
    the cells all 27), and K(theta) = sum_p theta_p K_p formed as block values on the list's
    one block pattern (the springs' and cells'), not as a sum of sparse matrices. On the
    93,705-node organ the four K_p take 0.36 GB (1.03 GB as CSR matrices, 0.68 GB on the full
    pattern each) and K(theta) 0.17 GB, where the sum of scaled copies built several 0.26 GB
    intermediates.

    Attributes:
        units: the K_p.
        n_blocks: blocks of the list's pattern; indices, indptr: that pattern.
    """

    units: tuple[_Unit, ...]
    n_blocks: int
    indices: np.ndarray
    indptr: np.ndarray

    @classmethod
    def of(cls, tangents: Iterable[sp.bsr_matrix]) -> UnitMatrices:
        """From the K_p assembled on one block pattern, taken one at a time (their zero blocks
        are dropped before the next is assembled)."""
        units: list[_Unit] = []
        indices = indptr = row = np.zeros(0, dtype=np.int32)
        n_blocks = 0
        for tangent in tangents:
            if not units:
                indices, indptr, n_blocks = tangent.indices, tangent.indptr, len(tangent.data)
                row = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
            assert np.array_equal(tangent.indices, indices)  # one block pattern
            positions = np.flatnonzero(np.any(tangent.data != 0.0, axis=(1, 2)))
            own = np.zeros_like(indptr)
            np.cumsum(np.bincount(row[positions], minlength=len(indptr) - 1), out=own[1:])
            units.append(
                _Unit(
                    values=np.ascontiguousarray(tangent.data[positions]),
                    positions=positions.astype(np.int32),
                    indices=np.ascontiguousarray(indices[positions]),
                    indptr=own,
                )
            )
        return cls(tuple(units), n_blocks, indices, indptr)

    def __len__(self) -> int:
        return len(self.units)

    def _bsr(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> sp.bsr_matrix:
        n = 3 * (len(indptr) - 1)
        return sp.bsr_matrix((data, indices, indptr), shape=(n, n), copy=False)

    def matrix(self, p: int) -> sp.bsr_matrix:
        """K_p on its own blocks (a view of the shared values: read only)."""
        u = self.units[p]
        return self._bsr(u.values, u.indices, u.indptr)

    def at(self, theta: np.ndarray) -> sp.bsr_matrix:
        """K(theta) = sum_p theta_p K_p (new values on the list's block pattern), summed a
        piece of :data:`SUM_PIECE` blocks at a time (whole, the products and the gathered
        blocks would be two more K(theta)-sized transients, 0.3 GB on the 93,705-node organ)."""
        values = np.zeros((self.n_blocks, 3, 3))
        for t, u in zip(np.asarray(theta, dtype=float), self.units, strict=True):
            for start in range(0, len(u.positions), SUM_PIECE):
                piece = slice(start, start + SUM_PIECE)
                values[u.positions[piece]] += t * u.values[piece]  # positions are distinct
        return self._bsr(values, self.indices, self.indptr)


_UNITS = threading.Lock()


def unit_matrices(
    problem: Problem, system: Any, units: list[Any], depth: int | None
) -> UnitMatrices:
    """The K_p of one perturbed list, linearised at rest: built once per (depth, list) and kept
    in ``problem.cache``, so that load cases with the same list and the chains running at once
    in one process share them (read only)."""
    key = (depth, system.free.tobytes())
    with _UNITS:
        cache = problem.cache.setdefault("reduced_units", {})
        if key not in cache:
            rest = np.zeros((system.n_free, 3))
            cache[key] = UnitMatrices.of(
                system.tangent(rest, system.parameters(s), modified=True) for s in units
            )
        return cache[key]


class ReducedLinearModel:
    """The linear lattice of every load case on a growing basis (this module's docstring).

    Args:
        cost: the static cost (its solver's lists, multigrid and linear solves are used).
        start: parameters whose response, and the directions in which it turns as each
            parameter grows, make the first basis.
    """

    def __init__(self, cost: StaticCost, start: list[float]):
        self.cost = cost
        self.problem: Problem = cost.problem
        self.solves = 0
        # K(theta) = sum_p c_p(theta) K_p: c = theta but for a transversely isotropic lattice
        units, self.coefficients = linear_parts(self.problem)
        n = len(units)
        solver = cost.solver
        self.cases: list[_Case] = []
        for j in range(len(self.problem.load_cases)):
            system, _ = solver.system(j, cost.depth)
            unit = unit_matrices(self.problem, system, units, cost.depth)
            loads = solver.loads(j)
            reference = cost.reference[j]
            moving = np.zeros(self.problem.n_nodes, dtype=bool)
            moving[system.free] = True
            held = float(np.linalg.norm(reference[~moving], axis=1).sum())
            self.cases.append(
                _Case(
                    free=system.free,
                    unit=unit,
                    loads=np.ascontiguousarray(loads[system.free]).ravel(),
                    reference=reference[system.free],
                    held=held,
                    basis=np.zeros((3 * system.n_free, 0)),
                    projected=np.zeros((n, 0, 0)),
                    rhs=np.zeros(0),
                )
            )
        theta = np.asarray(start, dtype=float)
        self.enrich(theta)
        # How the response turns as each parameter grows: du/dtheta_p = -K^-1 K_p u, taken as
        # one multigrid V-cycle on K_p u (a direction for the basis; exact solves come later).
        formed: dict[int, sp.bsr_matrix] = {}
        for j, case in enumerate(self.cases):
            assert case.last is not None
            matrix = self._matrix(case, theta, formed)
            for p in range(len(case.unit)):
                loads = np.zeros((self.problem.n_nodes, 3))
                loads[case.free] = (case.unit.matrix(p) @ case.last).reshape(-1, 3)
                turn = solver.linear_solve(j, cost.depth, matrix, loads, rtol=1.0)
                case.add(np.ascontiguousarray(turn[case.free]).ravel(), last=False)

    def enrich(self, theta: np.ndarray) -> None:
        """Add the full linear responses at ``theta`` to every load case's basis."""
        solver = self.cost.solver
        formed: dict[int, sp.bsr_matrix] = {}
        for j, case in enumerate(self.cases):
            guess = None
            if case.basis.shape[1]:  # start CG from the reduced model's answer
                guess = np.zeros((self.problem.n_nodes, 3))
                guess[case.free] = case.linear(self.coefficients(theta)).reshape(-1, 3)
            matrix = self._matrix(case, theta, formed)
            response = solver.linear_solve(
                j, self.cost.depth, matrix, solver.loads(j), guess=guess, rtol=RTOL
            )
            self.solves += 1
            case.add(np.ascontiguousarray(response[case.free]).ravel())

    def _matrix(
        self, case: _Case, theta: np.ndarray, formed: dict[int, sp.bsr_matrix]
    ) -> sp.bsr_matrix:
        """K(theta) of ``case``'s list, formed once per call site for the load cases that share
        the list's unit matrices (at full depth every case: 3 sums of 0.16 s each became one
        on the organ at h = 3 mm); ``formed`` keeps them by the unit matrices' identity."""
        key = id(case.unit)
        if key not in formed:
            formed[key] = case.unit.at(self.coefficients(theta))
        return formed[key]

    def __call__(self, theta: np.ndarray) -> float:
        """Eq. (2) of the reduced linear model over every load case, m."""
        c = self.coefficients(theta)
        return float(sum(case.cost(c) for case in self.cases))


DEFECT_ROUNDS = 8
"""At most this many rounds: a reduced fit, then a full linear and a static solve per load case
at its minimiser (the basis grows, the defect is renewed)."""


def fit_reduced(
    cost: StaticCost,
    start: list[float],
    bounds: tuple[np.ndarray, np.ndarray],
    model: ReducedLinearModel | None = None,
) -> tuple[list[float], float, ReducedLinearModel, np.ndarray | None]:
    """Minimise Eq. (2) of the nonlinear static equilibria within ``bounds`` from ``start``:
    reduced linear fits with enrichment, corrected by the nonlinear defect until the minimiser
    stops moving (this module's docstring).

    Returns (parameters, their normalised static cost (inf if a load case has no equilibrium),
    the model, the static equilibria at the parameters (L, N, 3), m, or None if one did not
    converge)."""
    model = ReducedLinearModel(cost, start) if model is None else model
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    y = np.clip(np.log(np.asarray(start, dtype=float)), lo, hi)
    static = float("inf")
    equilibria: np.ndarray | None = None
    step = FIRST_STEP
    for _ in range(DEFECT_ROUNDS):
        previous = y
        y = _reduced_minimum(model, y, lo, hi, step)
        step = max(min(step, 2 * float(np.abs(y - previous).max())), 10 * CONVERGED)
        theta = np.exp(y)
        model.enrich(theta)  # the full linear response at theta joins the basis
        solved = [cost.displacements(theta, j) for j in range(len(model.cases))]
        if not all(e.converged for e in solved):
            static, equilibria = float("inf"), None
            break
        equilibria = np.stack([e.displacements for e in solved])
        cost.evaluations += 1
        static = sum(cost.case_cost(j, e.displacements) for j, e in enumerate(solved))
        static /= cost.reference_cost
        for case, equilibrium in zip(model.cases, solved, strict=True):
            assert case.last is not None
            case.set_correction(equilibrium.displacements[case.free] - case.last.reshape(-1, 3))
        if float(np.abs(y - previous).max()) < CONVERGED:
            break
    return list(np.exp(y)), static, model, equilibria


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
