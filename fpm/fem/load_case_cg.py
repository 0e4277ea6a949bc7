"""Conjugate gradients for many load cases at once: the FEM's columns in lockstep.

Every load case is K u = f with the same K. Solved one after another, each CG iteration reads
all of K (and, in the preconditioner's smoothing sweeps, all of it again) for one vector; the
solve is bound by that reading, not by arithmetic. Here the load cases of a group move
together: each iteration multiplies K by all their search directions at once (one pass over
K for the group, SciPy's sparse times dense) and sweeps all of them in one pass
(:func:`block_gauss_seidel_columns`). Each column keeps its own CG (its own step lengths,
its own stop) and leaves the group when it has converged.

Bit for bit, a column's answer does not depend on which columns share its group: the sparse
products and the sweeps do per column what they do for one vector, in the same order, and the
dot products are sequential sums per column (:func:`column_dots`). So the groups can be shared
between threads (:func:`solve_columns`) and the answer is the same for any number of them.

Units are the caller's; shapes: n unknowns, c columns, (n, c) arrays.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import numpy as np
import scipy.sparse as sp

from .linear_solver import CgResult, NegativeCurvature

Preconditioner = Callable[[np.ndarray], np.ndarray]
"""(n, c) residuals -> (n, c) preconditioned residuals, column by column."""


def lockstep_cg(
    a: sp.sparray | sp.spmatrix,
    b: np.ndarray,
    precondition: Preconditioner,
    *,
    rtol: float,
    max_iterations: int,
    x0: np.ndarray | None = None,
) -> list[CgResult]:
    """Preconditioned CG for ``a`` (n, n) SPD and each column of ``b`` (n, c), from ``x0``
    (n, c) (None: zero), each until ||b_j - a x_j|| <= rtol ||b_j|| or ``max_iterations``.

    Raises:
        NegativeCurvature: a column met p.a p <= 0 (``a`` is not positive definite).
    """
    dots = _column_dots()
    n, c = b.shape
    results: list[CgResult | None] = [None] * c
    x = np.zeros((n, c)) if x0 is None else np.array(x0, dtype=float)
    r = b.copy() if x0 is None else b - a @ x
    norm_b = np.sqrt(dots(b, b))
    norm_r = np.sqrt(dots(r, r))
    live = np.arange(c)
    done = (norm_b == 0.0) | ((x0 is not None) & (norm_r <= rtol * norm_b))
    for j in np.flatnonzero(done):
        x_j = np.zeros(n) if norm_b[j] == 0.0 else x[:, j].copy()
        results[j] = CgResult(x_j, 0, 0.0 if norm_b[j] == 0.0 else norm_r[j] / norm_b[j], True)
    keep = ~done
    live, x, r = live[keep], x[:, keep], r[:, keep]
    z = precondition(r)
    p = z.copy()
    rz = dots(r, z)
    for it in range(1, max_iterations + 1):
        if not len(live):
            break
        q = a @ p
        pq = dots(p, q)
        if not np.all(pq > 0.0):
            raise NegativeCurvature(it)
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        norm_r = np.sqrt(dots(r, r))
        done = norm_r <= rtol * norm_b[live]
        for k in np.flatnonzero(done):
            j = live[k]
            results[j] = CgResult(x[:, k].copy(), it, norm_r[k] / norm_b[j], True)
        if done.any():
            keep = ~done
            live, x, r, p, rz = live[keep], x[:, keep], r[:, keep], p[:, keep], rz[keep]
            if not len(live):
                break
        z = precondition(r)
        rz, rz_old = dots(r, z), rz
        p *= rz / rz_old
        p += z
    if len(live):
        norm_r = np.sqrt(dots(r, r))
        for position, column in enumerate(live):
            residual = norm_r[position] / norm_b[column]
            results[column] = CgResult(x[:, position].copy(), max_iterations, residual, False)
    return [result for result in results if result is not None]


def solve_columns(
    a: sp.sparray | sp.spmatrix,
    b: np.ndarray,
    precondition: Preconditioner,
    *,
    rtol: float,
    max_iterations: int,
    threads: int,
    x0: np.ndarray | None = None,
) -> list[CgResult]:
    """:func:`lockstep_cg` of the columns of ``b`` (n, c), split into up to ``threads`` groups
    of consecutive columns, one thread each (the sparse products and the sweeps release the
    GIL). The answer is the same for any ``threads``. One preconditioning of a zero column
    first: it makes the multigrid's coarse solver, built on first use, before the threads
    share it."""
    c = b.shape[1]
    groups = [g for g in np.array_split(np.arange(c), min(max(threads, 1), c)) if len(g)]

    def group(columns: np.ndarray) -> list[CgResult]:
        start = None if x0 is None else x0[:, columns]
        return lockstep_cg(
            a, b[:, columns], precondition, rtol=rtol, max_iterations=max_iterations, x0=start
        )

    if len(groups) < 2:
        return group(np.arange(c))
    precondition(np.zeros((b.shape[0], 1)))
    with ThreadPoolExecutor(len(groups)) as pool:
        return [result for part in pool.map(group, groups) for result in part]


@cache
def _column_dots() -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """:func:`column_dots` compiled by numba (on first use)."""
    from numba import njit

    return njit(cache=True, nogil=True)(column_dots)


def column_dots(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(c,) u_j . v_j of the columns of ``u`` and ``v`` (n, c): a sequential sum per column,
    in row order, whatever c (no BLAS, no pairwise blocking that depends on the shape)."""
    n, c = u.shape
    out = np.zeros(c)
    for i in range(n):
        for j in range(c):
            out[j] += u[i, j] * v[i, j]
    return out


@cache
def compiled_sweep_columns() -> Callable[..., None]:
    """:func:`block_gauss_seidel_columns` compiled by numba (on first use)."""
    from numba import njit

    return njit(cache=True, nogil=True)(block_gauss_seidel_columns)


def block_gauss_seidel_columns(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    inverse: np.ndarray,
    x: np.ndarray,
    b: np.ndarray,
    forward: bool,
) -> None:
    """One forward (or backward) block Gauss-Seidel sweep for A x = b on every column of ``x``
    and ``b`` (3n, c) in place, A in 3x3 blocks (BSR arrays, sorted), ``inverse`` (n, 3, 3) the
    inverses of its diagonal blocks: each block read once for all columns, each column summed
    as :func:`fpm.fem.linear_solver._block_gauss_seidel` sums one vector."""
    n = len(indptr) - 1
    c = x.shape[1]
    t = np.empty((3, c))
    for step in range(n):
        i = step if forward else n - 1 - step
        t[:] = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if j != i:
                a = data[e]
                for v in range(c):
                    x0, x1, x2 = x[3 * j, v], x[3 * j + 1, v], x[3 * j + 2, v]
                    t[0, v] += a[0, 0] * x0 + a[0, 1] * x1 + a[0, 2] * x2
                    t[1, v] += a[1, 0] * x0 + a[1, 1] * x1 + a[1, 2] * x2
                    t[2, v] += a[2, 0] * x0 + a[2, 1] * x1 + a[2, 2] * x2
        d = inverse[i]
        for v in range(c):
            s0, s1, s2 = b[3 * i, v] - t[0, v], b[3 * i + 1, v] - t[1, v], b[3 * i + 2, v] - t[2, v]
            x[3 * i, v] = d[0, 0] * s0 + d[0, 1] * s1 + d[0, 2] * s2
            x[3 * i + 1, v] = d[1, 0] * s0 + d[1, 1] * s1 + d[1, 2] * s2
            x[3 * i + 2, v] = d[2, 0] * s0 + d[2, 1] * s1 + d[2, 2] * s2
