"""The lattice's slowest modes: ``K phi = w^2 M phi`` for a perturbed list's tangent at rest
(:mod:`fpm.dynamics.modes` reads the FPM step off them).

The k lowest (:func:`lowest_modes`), as Phi (3M, k) M-orthonormal (Phi^T M Phi = I; kg^-1/2)
and w^2 (k,) 1/s^2. Dense up to :data:`DENSE_UP_TO` unknowns; above, LOBPCG (Knyazev 2001)
preconditioned by one V-cycle of the static solver's multigrid hierarchy (an approximation of
K^-1, :mod:`fpm.fem.linear_solver`), started from the eigenvectors of a coarse level of that
hierarchy carried up to the lattice. The BLAS these dense products use is held to one thread
while the annealing chains' threads run (:func:`single_threaded_blas`).
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numba import njit

from ..fem.linear_solver import v_cycle

MODES = 16
"""Lowest modes the prediction keeps (docs/notes/2026-11-28-calibration-measured.md, *The
prediction's settings*)."""
EXTRA = 4
"""LOBPCG iterates this many vectors more than it keeps (the last ones converge slowest)."""
DENSE_UP_TO = 600
"""Unknowns up to which the modes come from a dense generalised eigensolve."""
COARSE_UP_TO = 600
"""LOBPCG starts from the eigenvectors of the finest multigrid level with at most this many
unknowns (a dense eigensolve there), carried up to the lattice."""
TOLERANCE = 0.1
"""LOBPCG stops once every kept mode's residual |K x - w^2 M x| is below this times |K x|."""
SETTLED_VALUES = 1e-3
"""LOBPCG also stops once no kept eigenvalue moved by more than this (relative) in an
iteration."""
MAX_ITERATIONS = 3
"""LOBPCG iterations at most on each level: the reduced step needs the slow modes' span more
than converged vectors."""

_BLAS_LOCK = threading.Lock()
_BLAS: list[tuple[Callable[[int], None], Callable[[], int]]] | None = None
_BLAS_USERS = [0, 0]  # [threads inside single_threaded_blas, the thread count to restore]


def _blas_controls() -> list[tuple[Callable[[int], None], Callable[[], int]]]:
    """(set, get) of the number of threads of each OpenBLAS loaded in this process (found in
    /proc/self/maps; none elsewhere)."""
    found: list[tuple[Callable[[int], None], Callable[[], int]]] = []
    try:
        with open("/proc/self/maps") as f:
            paths = sorted(
                {
                    line.split()[-1]
                    for line in f
                    if "openblas" in line.lower() and line.split()[-1].startswith("/")
                }
            )
    except OSError:
        return found
    names = (
        ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
        ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
        ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
        ("openblas_set_num_threads", "openblas_get_num_threads"),
    )
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for setter, getter in names:
            if hasattr(lib, setter) and hasattr(lib, getter):
                set_threads, get_threads = getattr(lib, setter), getattr(lib, getter)
                set_threads.argtypes, get_threads.restype = [ctypes.c_int], ctypes.c_int
                found.append((set_threads, get_threads))
                break
    return found


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run the block with OpenBLAS on one thread (its threads wait on each other on a busy
    machine; the dense algebra here is small or compiled)."""
    global _BLAS
    with _BLAS_LOCK:
        if _BLAS is None:
            _BLAS = _blas_controls()
        if _BLAS_USERS[0] == 0 and _BLAS:
            _BLAS_USERS[1] = _BLAS[0][1]()
            for set_threads, _ in _BLAS:
                set_threads(1)
        _BLAS_USERS[0] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_USERS[0] -= 1
            if _BLAS_USERS[0] == 0 and _BLAS:
                for set_threads, _ in _BLAS:
                    set_threads(_BLAS_USERS[1])


@dataclass
class Modes:
    """The k lowest modes of a list's tangent at rest (see the module docstring).

    Attributes:
        free: (M,) the list's nodes (the static solver's system order: ascending).
        w2: (k,) squared angular frequencies, 1/s^2, ascending.
        shapes: (3M, k) M-orthonormal mode shapes (node-major unknowns), kg^-1/2.
        kshapes: (3M, k) K times the shapes, N/m kg^-1/2 (the residual per unit amplitude).
        iterations: LOBPCG iterations (0: dense).
    """

    free: np.ndarray
    w2: np.ndarray
    shapes: np.ndarray
    kshapes: np.ndarray
    iterations: int = 0

    @property
    def frequencies(self) -> np.ndarray:
        """(k,) angular frequencies w, rad/s."""
        return np.sqrt(np.maximum(self.w2, 0.0))


def lowest_modes(
    tangent: sp.spmatrix | sp.sparray,
    masses: np.ndarray,
    count: int = MODES,
    *,
    hierarchy: object | None = None,
    free: np.ndarray | None = None,
    threads: int | None = None,
) -> Modes:
    """The ``count`` lowest modes of ``tangent`` (3M, 3M) N/m, symmetric positive definite,
    with lumped ``masses`` (M,) kg: K phi = w^2 M phi.

    Dense up to :data:`DENSE_UP_TO` unknowns. Above, level by level up ``hierarchy`` (a
    pyamg hierarchy of ``tangent``, required there; K_l = P^T K_{l-1} P, M_l likewise): a
    dense solve on the finest level of at most :data:`COARSE_UP_TO` unknowns, then LOBPCG on
    each finer level from the modes below, preconditioned by the V-cycle from that level down.
    ``threads``: the block's V-cycles on this many threads (None: :data:`CYCLE_THREADS`; the
    same bits on any number).
    """
    n = tangent.shape[0]
    m = np.repeat(np.asarray(masses, float), 3)
    count = min(count, n)
    nodes = np.arange(n // 3) if free is None else np.asarray(free)
    if n <= DENSE_UP_TO:
        scale = 1.0 / np.sqrt(m)
        a = tangent.toarray() * scale[:, None] * scale[None, :]
        w2, v = sla.eigh(a, subset_by_index=[0, count - 1])
        shapes = v * scale[:, None]
        return Modes(nodes, w2, shapes, np.asarray(tangent @ shapes), 0)
    if hierarchy is None:
        raise ValueError(f"{n} unknowns: the modes need a multigrid hierarchy")
    levels = hierarchy.levels  # type: ignore[attr-defined]
    block = min(count + EXTRA, n)
    masses_at = [sp.diags(m).tocsr()]
    for lvl in levels[:-1]:
        masses_at.append(sp.csr_matrix(lvl.P.T @ masses_at[-1] @ lvl.P))
    bottom = next(
        (i for i, lvl in enumerate(levels) if lvl.A.shape[0] <= COARSE_UP_TO), len(levels) - 1
    )
    take = min(block, levels[bottom].A.shape[0])
    _, x = sla.eigh(
        levels[bottom].A.toarray(), masses_at[bottom].toarray(), subset_by_index=[0, take - 1]
    )
    if take < block:  # a coarsest level too small: seeded random vectors fill the block
        rng = np.random.default_rng(0)
        x = np.hstack([x, rng.standard_normal((x.shape[0], block - take))])
    w2, kx, iterations = np.zeros(0), x, 0
    for level in range(bottom - 1, -1, -1):
        a_l, m_l = levels[level].A, masses_at[level]

        def precondition(r: np.ndarray, level: int = level) -> np.ndarray:
            return _cycles(hierarchy, r, level, threads)

        def stiffness(y: np.ndarray, a_l: sp.spmatrix = a_l) -> np.ndarray:
            return np.asarray(a_l @ y)

        def mass(y: np.ndarray, m_l: sp.spmatrix = m_l) -> np.ndarray:
            return np.asarray(m_l @ y)

        w2, x, kx, iterations = _lobpcg(
            stiffness,
            mass,
            precondition,
            precondition(mass(np.asarray(levels[level].P @ x))),
            count,
            MAX_ITERATIONS,
            m if level == 0 else None,  # the lattice's lumped masses: M is diagonal
        )
    return Modes(nodes, w2[:count], x[:, :count], kx[:, :count], iterations)


CYCLE_THREADS = 2
"""The V-cycles of a block (one per column) run on this many threads on levels of at least
:data:`THREADED_FROM` unknowns (the compiled smoother and SciPy's sparse products release the
GIL); each column's cycle is the same, bit for bit."""
THREADED_FROM = 20_000
"""Unknowns of a level from which its block's V-cycles are threaded (below, a cycle takes
well under a millisecond and the threads cost more than they save)."""


def _cycles(hierarchy: object, r: np.ndarray, level: int, threads: int | None = None) -> np.ndarray:
    """One V-cycle of ``hierarchy`` from ``level`` (:func:`fpm.fem.linear_solver.v_cycle`) on
    each column of ``r`` (n, b): (n, b), on ``threads`` threads (None: :data:`CYCLE_THREADS`).
    The first column's cycle runs alone (it sets up the coarsest level's solver, made on first
    use, before threads share it)."""
    threads = CYCLE_THREADS if threads is None else threads
    out = np.empty_like(r)

    def one(j: int) -> None:
        out[:, j] = v_cycle(hierarchy, np.ascontiguousarray(r[:, j]), level)  # type: ignore[arg-type]

    one(0)
    rest = range(1, r.shape[1])
    if threads < 2 or r.shape[0] < THREADED_FROM or len(rest) < 2:
        for j in rest:
            one(j)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(one, rest))
    return out


@njit(cache=True, nogil=True)
def _gram(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x^T y for tall x (n, a), y (n, b): (a, b); compiled, not a threaded BLAS (which waits on
    its threads on a busy machine)."""
    out = np.zeros((x.shape[1], y.shape[1]))
    _gram_into(out, x, y)
    return out


@njit(cache=True, nogil=True)
def _gram_into(out: np.ndarray, x: np.ndarray, y: np.ndarray) -> None:
    """out += x^T y, summed row after row (a sum continued over pieces of rows is the same, to
    the bit, as over all of them at once); :func:`_gram` is it on zeros."""
    n, a = x.shape
    b = y.shape[1]
    for i in range(n):
        for p in range(a):
            xp = x[i, p]
            for q in range(b):
                out[p, q] += xp * y[i, q]


@njit(cache=True, nogil=True)
def _weighted_gram(x: np.ndarray, m: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x^T diag(m) y for tall x (n, a), y (n, b), m (n,): (a, b); the products m_i y_iq are
    those of diag(m) @ y, summed as :func:`_gram` sums (the same bits as _gram(x, M y))."""
    n, a = x.shape
    b = y.shape[1]
    out = np.zeros((a, b))
    for i in range(n):
        mi = m[i]
        for p in range(a):
            xp = x[i, p]
            for q in range(b):
                out[p, q] += xp * (mi * y[i, q])
    return out


@njit(cache=True, nogil=True)
def _combine_into(out: np.ndarray, x: np.ndarray, c: np.ndarray) -> None:
    """out += x c for tall x (n, a) and small c (a, b), out (n, b); compiled (see
    :func:`_gram`): a sum continued block after block adds in the order one over the blocks
    side by side would."""
    n, a = x.shape
    b = c.shape[1]
    for i in range(n):
        for p in range(a):
            xp = x[i, p]
            for q in range(b):
                out[i, q] += xp * c[p, q]


def _combine(blocks: list[np.ndarray], c: np.ndarray) -> np.ndarray:
    """[B_0 B_1 ...] c for tall blocks B_i (n, a_i) side by side and small c (sum a_i, b):
    (n, b), without forming the blocks side by side."""
    out = np.zeros((blocks[0].shape[0], c.shape[1]))
    row = 0
    for b in blocks:
        _combine_into(out, b, np.ascontiguousarray(c[row : row + b.shape[1]]))
        row += b.shape[1]
    return out


def _lobpcg(
    apply: Callable[[np.ndarray], np.ndarray],
    mass: Callable[[np.ndarray], np.ndarray],
    precondition: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    count: int,
    iterations: int = MAX_ITERATIONS,
    diagonal: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Block LOBPCG for K x = w^2 M x (``apply``: K, ``mass``: M, on blocks of vectors):
    Rayleigh-Ritz on S = [X, T R, P] each iteration (R the residuals, T the preconditioner, P
    the last change of X orthogonal to X), until the first ``count`` residuals are below
    :data:`TOLERANCE` relative, or ``iterations``. ``diagonal``: M's diagonal (n,) where M is
    diagonal. S stays three blocks, its Gram matrices summed block by block, to hold at most
    five blocks at once. Returns (w^2, X, K X, iterations taken), ascending, X M-orthonormal."""
    block = x.shape[1]

    def m_gram(blocks: list[np.ndarray]) -> np.ndarray:
        """S^T M S of the blocks side by side."""
        sizes = np.cumsum([0] + [b.shape[1] for b in blocks])
        out = np.empty((sizes[-1], sizes[-1]))
        for j, bj in enumerate(blocks):
            mb = None if diagonal is not None else np.ascontiguousarray(mass(bj))
            for i in range(j + 1):
                if diagonal is not None:
                    g = _weighted_gram(blocks[i], diagonal, bj)
                else:
                    assert mb is not None
                    g = _gram(blocks[i], mb)
                out[sizes[i] : sizes[i + 1], sizes[j] : sizes[j + 1]] = g
                out[sizes[j] : sizes[j + 1], sizes[i] : sizes[i + 1]] = g.T
        return out

    def k_gram(blocks: list[np.ndarray], kfirst: np.ndarray) -> np.ndarray:
        """S^T K S, K applied to one block at a time (``kfirst``: K times the first)."""
        sizes = np.cumsum([0] + [b.shape[1] for b in blocks])
        out = np.empty((sizes[-1], sizes[-1]))
        for j, bj in enumerate(blocks):
            kb = kfirst if j == 0 else np.ascontiguousarray(apply(bj))
            for i in range(j + 1):
                g = _gram(blocks[i], kb)
                out[sizes[i] : sizes[i + 1], sizes[j] : sizes[j + 1]] = g
                out[sizes[j] : sizes[j + 1], sizes[i] : sizes[i + 1]] = g.T
            del kb
        return out

    def ritz(gm: np.ndarray, gk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the lowest ``block`` Ritz values, their coefficients on S): S made M-orthonormal
        (SVQB: the Gram matrix's eigenvectors, directions below 1e-10 of the largest dropped),
        then K's eigenproblem on it."""
        d = np.sqrt(np.maximum(np.diag(gm), 1e-300))
        e, v = np.linalg.eigh((gm + gm.T) / 2 / d[:, None] / d[None, :])
        keep = e > 1e-10 * e.max()
        c = (v[:, keep] / np.sqrt(e[keep])[None, :]) / d[:, None]
        a = c.T @ gk @ c
        w, y = np.linalg.eigh((a + a.T) / 2)
        return w[:block], c @ y[:, :block]

    x = np.ascontiguousarray(x)
    w, coefficients = ritz(m_gram([x]), k_gram([x], np.ascontiguousarray(apply(x))))
    x = _combine([x], coefficients)
    p: np.ndarray | None = None
    last: np.ndarray | None = None
    kx: np.ndarray | None = None
    taken = 0
    for taken in range(1, iterations + 1):
        kx = np.ascontiguousarray(apply(x))
        r = np.ascontiguousarray(mass(x))
        r *= -w[None, :]
        r += kx
        relative = np.linalg.norm(r[:, :count], axis=0) / np.linalg.norm(kx[:, :count], axis=0)
        settled = last is not None and np.all(np.abs(w[:count] / last - 1) <= SETTLED_VALUES)
        if settled or np.all(relative <= TOLERANCE):
            taken -= 1
            break
        last = w[:count].copy()
        t = np.ascontiguousarray(precondition(r))
        del r
        blocks = [x, t] if p is None else [x, t, p]
        gm = m_gram(blocks)
        gk = k_gram(blocks, kx)
        kx = None
        w, coefficients = ritz(gm, gk)
        new_x = _combine(blocks, coefficients)
        # P = new X - X (X^T M new X): the same combination with X's rows less X^T M S c
        change = gm[:block] @ coefficients
        coefficients[:block] -= change
        p = _combine(blocks, coefficients)
        x = new_x
        del blocks, t, new_x
    if kx is None:  # every iteration taken: K X of the last one
        kx = np.ascontiguousarray(apply(x))
    return w, x, kx, taken
