"""families+volume, stage 1: the fit on a reduced linear model (docs/physics.md, *Calibration*).

Linearised at rest, the lattice's stiffness matrix is linear in the fitted parameters:
``K(theta) = sum_p theta_p K_p`` (K_p: the matrix of family p's assembled springs at k = 1, and
of the cells at kappa = 1). Its response to a load case's forces f, ``u(theta) = K(theta)^-1 f``,
lies close to the span of a few responses at other parameters, so on a basis Q of such
responses (per load case, orthonormal) the reduced model

    u(theta) ~ Q (sum_p theta_p Q^T K_p Q)^-1 Q^T f

costs an m x m solve (m <= a few tens) instead of a sparse solve with 10^4-10^5 unknowns, and the
Eq. (2) cost of the linear model can be evaluated hundreds of times.

The model is nonlinear (springs rotate, cells change volume): the fit of the nonlinear cost
corrects the reduced model's displacements by the defect of the static equilibria, round by
round (:mod:`fpm.fitting.defect_correction`). The K_p are kept as their nonzero blocks, shared
in one process (:mod:`fpm.fitting.unit_matrices`).

Who does what in a calibration: the first basis (:func:`first_basis`: the response at the
chains' start and how it turns) depends on the lattice, the loads and the start only, so it is
built once (:class:`ReducedBasis`; the service's reduced-basis job, beside the FEM job); every
chain anneals the reduced cost on it (no full solve); the defect-corrected fit
(:func:`fpm.fitting.defect_correction.fit_reduced`) runs once, from the best chain's state, as
the damping stage's polish.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import scipy.sparse as sp
from numba import njit

from ..dynamics.eigen import single_threaded_blas
from ..dynamics.equilibrium import StaticSolver
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.problem import Problem
from ..model.stiffness import continuum_start, linear_parts
from .annealing import AnnealingError
from .bounds import fit_depth, stiffness_bounds
from .unit_matrices import UnitMatrices, unit_matrices

RTOL = 1e-6
"""Relative residual of the full linear solves that enrich the basis."""


@dataclass(frozen=True)
class CaseBasis:
    """One load case's first basis (:func:`first_basis`): what of its reduced model does not
    depend on the reference.

    Attributes:
        free: (M,) int64, the free nodes of the case's list, ascending.
        basis: (3M, m) orthonormal columns over them, node-major (x, y, z of free[0], ...).
        projected: (P, m, m) the K_p projected on the basis, Q^T K_p Q, N/m.
        rhs: (m,) the case's forces projected, Q^T f, N.
    """

    free: np.ndarray
    basis: np.ndarray
    projected: np.ndarray
    rhs: np.ndarray


@dataclass(frozen=True)
class ReducedBasis:
    """Every load case's first basis at the chains' start: the same for every chain of a
    calibration, so built once (the service's reduced-basis job, beside the FEM job) and handed
    to the chains and the damping stage (raw arrays through Redis: :meth:`to_stored`).

    Attributes:
        cases: one per load case.
        solves: full linear solves it took (one per load case; the turns are V-cycles).
    """

    cases: tuple[CaseBasis, ...]
    solves: int

    def to_stored(self) -> tuple[dict[str, Any], bytes]:
        """(the layout as a JSON-able dict, the arrays' raw bytes one after the other: per case
        free as int64, then basis, projected and rhs as float64)."""
        layout: dict[str, Any] = {"solves": self.solves, "cases": []}
        parts = []
        for case in self.cases:
            layout["cases"].append({"nodes": len(case.free), "columns": case.basis.shape[1],
                                    "parameters": case.projected.shape[0]})  # fmt: skip
            parts.append(np.ascontiguousarray(case.free, dtype=np.int64).tobytes())
            for a in (case.basis, case.projected, case.rhs):
                parts.append(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        return layout, b"".join(parts)

    @classmethod
    def from_stored(cls, layout: dict[str, Any], raw: bytes) -> ReducedBasis:
        """The basis back from :meth:`to_stored`'s layout and bytes (the same bits)."""
        cases, offset = [], 0

        def take(shape: tuple[int, ...], dtype: type[np.generic]) -> np.ndarray:
            nonlocal offset
            size = int(np.prod(shape)) * 8
            a = np.frombuffer(raw, dtype=dtype, count=size // 8, offset=offset).reshape(shape)
            offset += size
            return a.copy()

        for c in layout["cases"]:
            n, m, p = c["nodes"], c["columns"], c["parameters"]
            free = take((n,), np.int64)
            basis, projected = take((3 * n, m), np.float64), take((p, m, m), np.float64)
            cases.append(CaseBasis(free, basis, projected, take((m,), np.float64)))
        if offset != len(raw):
            raise ValueError(f"a stored reduced basis of {len(raw)} bytes, its layout {offset}")
        return cls(tuple(cases), int(layout["solves"]))


@dataclass
class _Case:
    """One load case's reduced model: basis (3M, m) over its free nodes, K_p projected, f; the
    reference where the cost is wanted (:meth:`ReducedLinearModel.of`), the unit matrices and
    loads where the basis grows (:meth:`ReducedLinearModel.attach`)."""

    free: np.ndarray
    basis: np.ndarray  # (3M, m)
    projected: np.ndarray  # (P, m, m)
    rhs: np.ndarray  # (m,)
    reference: np.ndarray | None = None  # (M, 3) reference displacements of the free nodes
    held: float = 0.0  # sum of |reference| over the nodes that do not move in this list
    unit: UnitMatrices | None = None  # the K_p
    loads: np.ndarray | None = None  # (3M,)
    correction: np.ndarray | None = None  # (M, 3) nonlinear minus linear displacements
    last: np.ndarray | None = None  # (3M,) the last full linear response added
    offset: np.ndarray | None = None  # (M, 3) correction minus reference (set by :meth:`cost`)

    @classmethod
    def of(cls, basis: CaseBasis, reference: np.ndarray) -> _Case:
        """The case of ``basis`` against ``reference`` (N, 3), m."""
        moving = np.zeros(len(reference), dtype=bool)
        moving[basis.free] = True
        held = float(np.linalg.norm(reference[~moving], axis=1).sum())
        return cls(basis.free, basis.basis, basis.projected, basis.rhs,
                   reference=reference[basis.free], held=held)  # fmt: skip

    def stored(self) -> CaseBasis:
        """The basis as it stands (:class:`CaseBasis`)."""
        return CaseBasis(self.free, self.basis, self.projected, self.rhs)

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
        assert self.unit is not None and self.loads is not None  # attached
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
        from y, the correction, the distance to the reference, summed."""
        a = np.einsum("p,pab->ab", theta, self.projected)
        try:
            y = np.linalg.solve(a, self.rhs)
        except np.linalg.LinAlgError:
            return float("inf")
        if self.offset is None:
            assert self.reference is not None
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


class ReducedLinearModel:
    """The linear lattice of every load case on a growing basis (this module's docstring):
    Eq. (2) of the reduced model at any theta (:meth:`__call__`, given the reference by
    :meth:`of`); once :meth:`attach` ed to a static solver, :meth:`enrich` grows the bases by
    full linear solves.

    Args:
        problem: the problem.
        cases: one per load case.
    """

    def __init__(self, problem: Problem, cases: list[_Case]):
        self.problem = problem
        self.cases = cases
        self.solves = 0
        # K(theta) = sum_p c_p(theta) K_p: c = theta but for a transversely isotropic lattice
        self.parts, self.coefficients = linear_parts(problem)
        self.solvers: list[StaticSolver] = []
        self.depth: int | None = None

    @classmethod
    def of(cls, problem: Problem, basis: ReducedBasis, reference: np.ndarray) -> ReducedLinearModel:
        """The model on ``basis`` whose cost measures against ``reference`` (L, N, 3), m."""
        cases = [_Case.of(b, reference[j]) for j, b in enumerate(basis.cases)]
        return cls(problem, cases)

    def attach(self, solvers: Sequence[StaticSolver], depth: int | None) -> None:
        """Give each case what its basis grows by: its list's unit matrices (shared through
        ``problem.cache.reduced_units``: :func:`unit_matrices`) and loads, and ``solvers[j]``
        for load case j's linear solves at ``depth`` (its multigrid hierarchies serve them; one
        solver may serve several cases)."""
        self.solvers, self.depth = list(solvers), depth
        for j, case in enumerate(self.cases):
            system, _ = self.solvers[j].system(j, depth)
            assert np.array_equal(system.free, case.free)
            case.unit = unit_matrices(self.problem, system, self.parts, depth)
            case.loads = np.ascontiguousarray(self.solvers[j].loads(j)[system.free]).ravel()

    def basis(self) -> ReducedBasis:
        """The bases as they stand (:class:`ReducedBasis`)."""
        return ReducedBasis(tuple(case.stored() for case in self.cases), self.solves)

    def enrich(self, theta: np.ndarray) -> None:
        """Add the full linear responses at ``theta`` to every load case's basis."""
        self.add(self.responses(theta))

    def responses(self, theta: np.ndarray) -> list[Callable[[], np.ndarray]]:
        """Per load case, the full linear solve at ``theta`` as a call returning its response
        (3M,) over the case's free nodes (CG from the reduced model's answer): a call touches
        only its case's solver, so calls on different solvers may run at once on threads;
        :meth:`add` them."""
        formed: dict[int, sp.bsr_matrix] = {}
        calls: list[Callable[[], np.ndarray]] = []
        for j, case in enumerate(self.cases):
            guess = None
            if case.basis.shape[1]:  # start CG from the reduced model's answer
                guess = np.zeros((self.problem.n_nodes, 3))
                guess[case.free] = case.linear(self.coefficients(theta)).reshape(-1, 3)
            calls.append(partial(self._response, j, self._matrix(case, theta, formed), guess))
        return calls

    def _response(self, j: int, matrix: sp.bsr_matrix, guess: np.ndarray | None) -> np.ndarray:
        """Load case j's full linear response to its loads under ``matrix``, (3M,)."""
        solver = self.solvers[j]
        response = solver.linear_solve(
            j, self.depth, matrix, solver.loads(j), guess=guess, rtol=RTOL
        )
        return np.ascontiguousarray(response[self.cases[j].free]).ravel()

    def add(self, responses: Iterable[Callable[[], np.ndarray] | np.ndarray]) -> None:
        """Add each load case's full linear response (or the call that returns it), in case
        order, to its basis."""
        for case, response in zip(self.cases, responses, strict=True):
            self.solves += 1
            case.add(response() if callable(response) else response)

    def turn(self, theta: np.ndarray) -> None:
        """Add how each case's last response turns as each parameter grows,
        du/dtheta_p = -K^-1 K_p u, taken as one multigrid V-cycle on K_p u (a direction for
        the basis; exact solves come later)."""
        formed: dict[int, sp.bsr_matrix] = {}
        for j, case in enumerate(self.cases):
            assert case.last is not None and case.unit is not None
            matrix = self._matrix(case, theta, formed)
            for p in range(len(case.unit)):
                loads = np.zeros((self.problem.n_nodes, 3))
                loads[case.free] = (case.unit.matrix(p) @ case.last).reshape(-1, 3)
                turn = self.solvers[j].linear_solve(j, self.depth, matrix, loads, rtol=1.0)
                case.add(np.ascontiguousarray(turn[case.free]).ravel(), last=False)

    def _matrix(
        self, case: _Case, theta: np.ndarray, formed: dict[int, sp.bsr_matrix]
    ) -> sp.bsr_matrix:
        """K(theta) of ``case``'s list, formed once per call site for the load cases that share the
        list's unit matrices (at full depth every case); ``formed`` keeps them by the unit matrices'
        identity. Its indices sorted here, so that the solves sharing it on threads only read it (a
        hierarchy built on it would sort them in place)."""
        assert case.unit is not None  # attached
        key = id(case.unit)
        if key not in formed:
            formed[key] = case.unit.at(self.coefficients(theta))
            formed[key].sort_indices()
        return formed[key]

    def __call__(self, theta: np.ndarray) -> float:
        """Eq. (2) of the reduced linear model over every load case, m."""
        c = self.coefficients(theta)
        return float(sum(case.cost(c) for case in self.cases))


def chain_start(problem: Problem) -> list[float]:
    """Where families+volume chains start, and their first basis is built: the continuum
    start (:func:`fpm.model.stiffness.continuum_start`) inside the stiffness bounds."""
    lower, upper = stiffness_bounds(problem)
    return list(np.clip(continuum_start(problem), lower, upper))


def first_basis(problem: Problem) -> ReducedBasis:
    """Every load case's first basis at :func:`chain_start`, at the depth the chains fit at:
    the full linear response there and how it turns as each parameter grows (one linear solve
    and P V-cycles per load case). It depends on the lattice, the loads and the start only,
    not on the reference. Built on a static solver of its own (whoever takes the basis solves
    on a solver it did not touch, so the answers do not depend on who built it) with one BLAS
    thread (the same bits in a chain, the damping stage or a job of their own)."""
    with single_threaded_blas():
        solver = StaticSolver(problem)
        depth = fit_depth(problem)
        n = len(linear_parts(problem)[0])
        cases = []
        for j in range(len(problem.load_cases)):
            system, _ = solver.system(j, depth)
            cases.append(_Case(system.free, np.zeros((3 * system.n_free, 0)),
                               np.zeros((n, 0, 0)), np.zeros(0)))  # fmt: skip
        model = ReducedLinearModel(problem, cases)
        model.attach([solver] * len(cases), depth)
        theta = np.asarray(chain_start(problem), dtype=float)
        try:
            model.enrich(theta)
        except (SingularStiffnessError, NegativeCurvature) as e:
            raise AnnealingError(
                f"the lattice linearised at the chains' start (k {_fmt(theta[:-1])} N/m, kappa "
                f"{theta[-1]:.3g} Pa) is singular in double precision ({e}): its springs are "
                "too soft beside its volume term to hold it; widen annealing.bounds.k, or check "
                "E and the units (E in Pa, lengths in m)"
            ) from None
        model.turn(theta)
        return model.basis()


def _fmt(values: np.ndarray) -> str:
    return " / ".join(f"{v:.3g}" for v in values)
