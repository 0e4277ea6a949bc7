"""Sparse linear solves shared by the FEM and the FPM's static equilibrium.

The FEM solves K X = F for many load cases with one factorisation (paper Sec. 4.1,
``F = K X``) by one of two methods, chosen by size (``"auto"``), measured in
``bench/bench_fem.py``:

- ``"direct"``: sparse LU (SuperLU, symmetric mode, minimum-degree ordering on K + K^T).
  Exact to round-off; its fill-in grows fast with size on 3-D meshes.
- ``"amg"``: conjugate gradients preconditioned by smoothed-aggregation algebraic multigrid
  (pyamg) built with the six rigid-body modes as near-null space, so that aggregates keep
  rotations as well as translations, on 3x3 node blocks. Memory and time grow about linearly
  with size.

The factorisation (or multigrid hierarchy) is built once and reused for every load case.

The pieces of ``"amg"`` are used on their own by :mod:`fpm.dynamics.equilibrium` (Newton steps
on the springs' tangent): :func:`amg_hierarchy` (the one hierarchy setup, its finest level
smoothed by a compiled 3x3 block Gauss-Seidel), :func:`v_cycle` (the preconditioner),
:func:`conjugate_gradients` (tolerance, iteration limit, per-node stop, negative-curvature
detection) and :func:`dot`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, partial
from typing import NamedTuple

import numpy as np
import pyamg
import scipy.sparse as sp
from pyamg.util.utils import get_block_diag
from scipy.sparse.linalg import splu

AMG_FROM_UNKNOWNS = 5_000
"""``"auto"`` uses AMG from this many unknowns on (bench/bench_fem.py)."""

AMG_TOLERANCE = 1e-9
"""The FEM's relative residual ||K x - f|| / ||f|| at which conjugate gradients stops."""

AMG_MAX_ITERATIONS = 1000
"""The FEM's CG iterations per load case before giving up."""

COMPILED_SMOOTHER_FROM = 50_000
"""The FEM's ``"amg"`` smooths with the compiled sweep (:func:`amg_hierarchy`) from this many
unknowns on: below, the sweep's start-up once per process (importing numba, loading the
compiled code) outweighs what it saves (bench/bench_fem.py)."""


class SingularStiffnessError(ValueError):
    """The reduced stiffness matrix is singular: some part of the solid is not held."""


class NegativeCurvature(ArithmeticError):
    """CG met a direction of non-positive curvature; ``args[0]`` is the iterations done."""


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """(3P, 6) nodal displacements of the 3 translations and 3 rotations of ``points`` (P, 3), m.

    Unknowns are node-major (u0, v0, w0, u1, ...). Rotations are about the points' centroid.
    """
    x = points - points.mean(axis=0)
    modes = np.zeros((len(points), 3, 6))
    modes[:, [0, 1, 2], [0, 1, 2]] = 1.0
    for mode, (a, b) in enumerate(((0, 1), (1, 2), (2, 0)), start=3):  # rotation in the a-b plane
        modes[:, a, mode] = -x[:, b]
        modes[:, b, mode] = x[:, a]
    return modes.reshape(-1, 6)


def choose_method(n_unknowns: int) -> str:
    """``"direct"`` below :data:`AMG_FROM_UNKNOWNS` unknowns, else ``"amg"``."""
    return "direct" if n_unknowns < AMG_FROM_UNKNOWNS else "amg"


def factorize(
    k: sp.bsr_matrix | sp.csr_matrix, method: str, near_null_space: np.ndarray
) -> Callable[[np.ndarray], np.ndarray]:
    """Prepare to solve ``k`` (n, n) SPD; returns a function F (n, L) -> X (n, L).

    Args:
        k: reduced stiffness matrix, N/m; in 3x3 node blocks (BSR) when whole nodes are free,
            which lets AMG aggregate nodes rather than single unknowns.
        method: ``"direct"`` or ``"amg"``.
        near_null_space: (n, 6) rigid-body modes of the free unknowns (used by ``"amg"``).

    ``"amg"`` solves each column by :func:`conjugate_gradients` to :data:`AMG_TOLERANCE` in at
    most :data:`AMG_MAX_ITERATIONS` iterations; the caller checks the residual.

    Raises:
        SingularStiffnessError: the LU factorisation found an exactly singular matrix, or (when
            solving) CG found ``k`` not positive definite.
    """
    if method == "direct":
        try:
            lu = splu(
                k.tocsc(),
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as e:  # "Factor is exactly singular"
            raise SingularStiffnessError(str(e)) from None
        return lambda f: lu.solve(np.asarray(f, dtype=float))
    if method == "amg":
        compiled = k.shape[0] >= COMPILED_SMOOTHER_FROM
        cycle = partial(v_cycle, amg_hierarchy(k, near_null_space, compiled=compiled))

        def solve(f: np.ndarray) -> np.ndarray:
            try:
                return np.stack([r.x for r in each_column(k, list(f.T), cycle)], axis=1)
            except NegativeCurvature:
                raise SingularStiffnessError("CG: the matrix is not positive definite") from None

        return solve
    raise ValueError(f"unknown method {method!r} (use 'direct', 'amg' or 'auto')")


COLUMN_THREADS = 2
"""The load cases' CG solves run on this many threads at once (the compiled smoother and
SciPy's sparse products release the GIL): each column is the same solve, bit for bit, as alone,
in less wall time for the same CPU time."""


def each_column(
    k: sp.sparray | sp.spmatrix,
    columns: list[np.ndarray],
    cycle: Callable[[np.ndarray], np.ndarray],
    rtol: float = AMG_TOLERANCE,
    starts: list[np.ndarray] | None = None,
) -> list[CgResult]:
    """:func:`conjugate_gradients` of ``k`` to ``rtol`` for each right-hand side in
    ``columns`` (from ``starts``, one per column, None: from 0), on up to
    :data:`COLUMN_THREADS` threads (one preconditioning first, which sets up the hierarchy's
    coarse solver, made on first use, before the threads share it)."""
    x0s: list[np.ndarray | None] = [None] * len(columns) if starts is None else list(starts)

    def one(b: np.ndarray, x0: np.ndarray | None) -> CgResult:
        return conjugate_gradients(k, b, cycle, rtol=rtol, x0=x0)

    if len(columns) < 2 or COLUMN_THREADS < 2:
        return [one(b, x0) for b, x0 in zip(columns, x0s, strict=True)]
    from concurrent.futures import ThreadPoolExecutor

    cycle(np.zeros(k.shape[0]))
    with ThreadPoolExecutor(min(COLUMN_THREADS, len(columns))) as pool:
        return list(pool.map(one, columns, x0s))


def amg_hierarchy(
    k: sp.bsr_matrix | sp.csr_matrix, near_null_space: np.ndarray, *, compiled: bool = True
) -> pyamg.MultilevelSolver:
    """Smoothed-aggregation hierarchy of ``k`` (n, n) SPD, for :func:`v_cycle`.

    ``near_null_space``: (n, 6) rigid-body modes (:func:`rigid_body_modes`). ``k`` in 3x3 node
    blocks (BSR) aggregates nodes; any other format is converted to CSR. One forward block
    Gauss-Seidel sweep before the coarse correction, one backward after. ``compiled``: on a
    finest level in 3x3 blocks, sweep with :func:`_block_gauss_seidel` compiled by numba
    (pyamg's sweeps bit for bit; compiled on first use, see :data:`COMPILED_SMOOTHER_FROM`).
    Sorts the indices of a BSR
    ``k`` in place.
    """
    hierarchy = pyamg.smoothed_aggregation_solver(
        k if k.format == "bsr" else k.tocsr(),
        B=near_null_space,
        symmetry="symmetric",
        improve_candidates=None,  # the rigid-body modes are exact: no need to smooth them
        # Gershgorin row weights instead of a spectral-radius estimate: deterministic (the
        # estimate starts from np.random) and no threaded BLAS.
        smooth=("jacobi", {"weighting": "local"}),
        # one forward sweep before, one backward after: a symmetric V-cycle, as CG needs
        presmoother=("block_gauss_seidel", {"sweep": "forward"}),
        postsmoother=("block_gauss_seidel", {"sweep": "backward"}),
    )
    finest = hierarchy.levels[0]
    a = finest.A
    if compiled and len(hierarchy.levels) > 1 and a.format == "bsr" and a.blocksize == (3, 3):
        a.sort_indices()
        inverse = get_block_diag(a, blocksize=3, inv_flag=True)
        sweep = _compiled_sweep()
        finest.presmoother = partial(_smooth, sweep=sweep, inverse=inverse, forward=True)
        finest.postsmoother = partial(_smooth, sweep=sweep, inverse=inverse, forward=False)
    return hierarchy


def _smooth(
    a: sp.bsr_matrix,
    x: np.ndarray,
    b: np.ndarray,
    *,
    sweep: Callable[..., None],
    inverse: np.ndarray,
    forward: bool,
) -> None:
    """One block Gauss-Seidel sweep on ``x`` in place (the V-cycle's smoother signature)."""
    sweep(a.indptr, a.indices, a.data, inverse, x, b, forward)


@cache
def _compiled_sweep() -> Callable[..., None]:
    """:func:`_block_gauss_seidel` compiled by numba, imported on first use: the FEM's LU path
    and its smaller AMG solves do without it (its import costs time and memory)."""
    from numba import njit

    return njit(cache=True, nogil=True)(_block_gauss_seidel)


def _block_gauss_seidel(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    inverse: np.ndarray,
    x: np.ndarray,
    b: np.ndarray,
    forward: bool,
) -> None:
    """One forward (or backward) block Gauss-Seidel sweep for A x = b, A in 3x3 blocks (BSR
    arrays, sorted), ``inverse`` (n, 3, 3) the inverses of its diagonal blocks. Sums in
    pyamg's order (the off-diagonal products first, then b minus them), so as to match it bit
    for bit."""
    n = len(indptr) - 1
    for step in range(n):
        i = step if forward else n - 1 - step
        t0 = t1 = t2 = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if j != i:
                x0, x1, x2 = x[3 * j], x[3 * j + 1], x[3 * j + 2]
                t0 += data[e, 0, 0] * x0 + data[e, 0, 1] * x1 + data[e, 0, 2] * x2
                t1 += data[e, 1, 0] * x0 + data[e, 1, 1] * x1 + data[e, 1, 2] * x2
                t2 += data[e, 2, 0] * x0 + data[e, 2, 1] * x1 + data[e, 2, 2] * x2
        s0, s1, s2 = b[3 * i] - t0, b[3 * i + 1] - t1, b[3 * i + 2] - t2
        d = inverse[i]
        x[3 * i] = d[0, 0] * s0 + d[0, 1] * s1 + d[0, 2] * s2
        x[3 * i + 1] = d[1, 0] * s0 + d[1, 1] * s1 + d[1, 2] * s2
        x[3 * i + 2] = d[2, 0] * s0 + d[2, 1] * s1 + d[2, 2] * s2


def v_cycle(hierarchy: pyamg.MultilevelSolver, b: np.ndarray, level: int = 0) -> np.ndarray:
    """One multigrid V-cycle from x = 0 for A x = b on ``level``: smooth, correct, smooth."""
    lvl = hierarchy.levels[level]
    if level == len(hierarchy.levels) - 1:
        return np.asarray(hierarchy.coarse_solver(lvl.A, b)).reshape(b.shape)
    x = np.zeros_like(b)
    lvl.presmoother(lvl.A, x, b)
    x += lvl.P @ v_cycle(hierarchy, lvl.R @ (b - lvl.A @ x), level + 1)
    lvl.postsmoother(lvl.A, x, b)
    return x


class CgResult(NamedTuple):
    """What :func:`conjugate_gradients` reached."""

    x: np.ndarray
    """The solution."""
    iterations: int
    """Iterations taken."""
    residual: float
    """||b - a x|| / ||b|| (0 when b = 0)."""
    converged: bool
    """It stopped on a tolerance (relative or per node), not on the iteration limit."""


REBUILD_SLOWDOWN = 2.0
"""Rebuild a reused multigrid hierarchy when CG needs this many times the iterations per digit
it needed on the matrix the hierarchy was built on (plus a few)."""


@dataclass
class ReusedHierarchy:
    """A smoothed-aggregation hierarchy built on one matrix and reused for later ones (Newton's
    tangents) while CG stays fast.

    ``digit_cost`` is the CG iterations per decimal digit of residual reduction measured on
    the first solve after the build; a later solve much slower than that marks it ``stale``
    (its owner then builds a new one). Used by the static FPM equilibrium and the neo-Hookean
    FEM.
    """

    hierarchy: pyamg.MultilevelSolver
    digit_cost: float | None = None
    stale: bool = False
    uses: int = 0

    def precondition(self, b: np.ndarray) -> np.ndarray:
        return v_cycle(self.hierarchy, b)

    def record(self, iterations: int, reduction: float, converged: bool) -> None:
        """Note one CG solve: ``iterations`` taken to reduce the residual by ``reduction``;
        ``converged``: it stopped before the iteration limit. (Short solves, which stop on a
        nodal criterion after little reduction, are no evidence of a slowdown.)"""
        cost = iterations / max(-math.log10(max(reduction, 1e-300)), 0.25)
        self.uses += 1
        if not converged:
            self.stale = True
        elif self.digit_cost is None:
            self.digit_cost = cost
        elif iterations >= 5 and cost > REBUILD_SLOWDOWN * self.digit_cost + 2.0:
            self.stale = True


def conjugate_gradients(
    a: sp.sparray | sp.spmatrix,
    b: np.ndarray,
    precondition: Callable[[np.ndarray], np.ndarray],
    *,
    rtol: float = AMG_TOLERANCE,
    max_iterations: int = AMG_MAX_ITERATIONS,
    nodal_stop: float = 0.0,
    x0: np.ndarray | None = None,
) -> CgResult:
    """Preconditioned CG from ``x0`` (n,) (None: x = 0) for ``a`` (n, n) SPD until
    ||b - a x|| <= rtol ||b||, or,
    with ``nodal_stop`` > 0, until every node's residual (3 consecutive unknowns) has a norm of
    at most ``nodal_stop``; stops quietly after ``max_iterations`` (``converged`` False).

    Hand-written rather than pyamg's or scipy's so that no step calls multithreaded BLAS: on a
    busy machine a threaded dot product waits for its threads far longer than one thread takes.

    Raises:
        NegativeCurvature: a search direction p with p.a p <= 0 (``a`` is not positive
            definite); ``args[0]`` is the iterations done.
    """
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=float)
    norm_b = math.sqrt(dot(b, b))
    if norm_b == 0.0:
        return CgResult(np.zeros_like(b), 0, 0.0, True)
    r = b.copy() if x0 is None else b - a @ x
    if x0 is not None and math.sqrt(dot(r, r)) <= rtol * norm_b:  # the start is the answer
        return CgResult(x, 0, math.sqrt(dot(r, r)) / norm_b, True)
    z = precondition(r)
    p = z.copy()
    rz = dot(r, z)
    stop = rtol * norm_b
    nodal2 = nodal_stop * nodal_stop
    norm_r = norm_b
    for it in range(1, max_iterations + 1):
        q = a @ p
        pq = dot(p, q)
        if not pq > 0.0:
            raise NegativeCurvature(it)
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        norm_r = math.sqrt(dot(r, r))
        if norm_r <= stop:
            return CgResult(x, it, norm_r / norm_b, True)
        if nodal2 > 0.0 and norm_r * norm_r <= nodal2 * (len(r) // 3):  # necessary for it
            per_node = r.reshape(-1, 3)
            if np.einsum("ij,ij->i", per_node, per_node).max() <= nodal2:
                return CgResult(x, it, norm_r / norm_b, True)
        z = precondition(r)
        rz, rz_old = dot(r, z), rz
        p *= rz / rz_old
        p += z
    return CgResult(x, max_iterations, norm_r / norm_b, False)


def dot(u: np.ndarray, v: np.ndarray) -> float:
    """u . v of two vectors without BLAS (see :func:`conjugate_gradients`)."""
    return float(np.einsum("i,i->", u, v))
