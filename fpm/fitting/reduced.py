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

Who does what in a calibration: the first basis (:func:`first_basis`: the response at the
chains' start and how it turns) depends on the lattice, the loads and the start only, so it is
built once (:class:`ReducedBasis`; the service's reduced-basis job, beside the FEM job); every
chain anneals the reduced cost on it (no full solve); the defect-corrected fit
(:func:`fit_reduced`) runs once, from the best chain's state, as the damping stage's polish.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.optimize import minimize

from ..dynamics.equilibrium import Equilibrium, StaticSolver
from ..dynamics.modes import single_threaded_blas
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.stiffness import continuum_start, linear_parts, model_stiffness
from .annealing import AnnealingError
from .bounds import fit_depth, stiffness_bounds
from .cost import StaticCost

CONVERGED = 2e-3
"""The fit has converged when no parameter moved more than this (relative) in a round."""
FIRST_STEP = 0.2
"""The first reduced fit's Nelder-Mead simplex, log units (later ones: twice the last move)."""
RTOL = 1e-6
"""Relative residual of the full linear solves that enrich the basis."""
MAX_EVALUATIONS = 400
"""Nelder-Mead evaluations of the reduced cost per round."""


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
        from y, the correction, the distance to the reference, summed. Evaluated hundreds of
        times per round, it was 44% of a chain's time on the organ at h = 3 mm as NumPy
        (the matrix-vector product on a threaded BLAS and the temporaries of the norms)."""
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
        ``problem.cache``: :func:`unit_matrices`) and loads, and ``solvers[j]`` for load case
        j's linear solves at ``depth`` (its multigrid hierarchies serve them; one solver may
        serve several cases)."""
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
        """K(theta) of ``case``'s list, formed once per call site for the load cases that share
        the list's unit matrices (at full depth every case: 3 sums of 0.16 s each became one
        on the organ at h = 3 mm); ``formed`` keeps them by the unit matrices' identity. Its
        indices sorted here, so that the solves sharing it on threads only read it (a
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


DEFECT_ROUNDS = 8
"""At most this many rounds: a reduced fit, then a full linear and a static solve per load case
at its minimiser (the basis grows, the defect is renewed)."""


CASE_SOLVERS = 2
"""A round of :func:`fit_reduced` splits its solves over this many static solvers, each
solving its share one after the other on a thread of its own: solver 0 (the cost's) every
load case's full linear response (a CG from the reduced model's answer: after the first round
a tenth of a static solve) and case 0's static equilibrium, the others the other cases'
static equilibria in turn. On the organ at h = 3 mm the fit took 3.75-4.0 instead of 5.5 s on
a quiet 2-core machine with case j wholly on solver j mod 2; with this split the 93,705-node
organ's rounds are closer to even (static solves 2-6 s, responses 0.1-4.6 s). The answer does
not depend on the threads (a solver's solves always run in the same order); each more solver
would hold a multigrid hierarchy and a tangent buffer more (a third: +420 MiB at 93,705
nodes, for 2.4 s)."""


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

    Returns (parameters, their normalised static cost (inf if a load case has no equilibrium),
    the full linear solves it made)."""
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
                static = float("inf")
                break
            cost.evaluations += 1
            static = sum(cost.case_cost(j, e.displacements) for j, e in enumerate(solved))
            static /= cost.reference_cost
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
