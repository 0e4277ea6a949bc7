"""Solving K X = F for many load cases with one factorisation (paper Sec. 4.1, ``F = K X``).

Two methods, chosen by size (``"auto"``), measured in ``bench/bench_fem.py``:

- ``"direct"``: sparse LU (SuperLU, symmetric mode, minimum-degree ordering on K + K^T).
  Exact to round-off; its fill-in grows fast with size on 3-D meshes.
- ``"amg"``: conjugate gradients preconditioned by smoothed-aggregation algebraic multigrid
  (pyamg) built with the six rigid-body modes as near-null space, so that aggregates keep
  rotations as well as translations, on 3x3 node blocks. Memory and time grow about linearly
  with size.

The factorisation (or multigrid hierarchy) is built once and reused for every load case.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
import pyamg
import scipy.sparse as sp
from scipy.sparse.linalg import splu

AMG_FROM_UNKNOWNS = 5_000
"""``"auto"`` uses AMG from this many unknowns on (see bench/bench_fem.py for the crossover)."""

AMG_TOLERANCE = 1e-9
"""Relative residual ||K x - f|| / ||f|| at which conjugate gradients stops."""

AMG_MAX_ITERATIONS = 1000
"""Conjugate-gradient iterations per load case before giving up (a well-held solid needs ~50)."""


class SingularStiffnessError(ValueError):
    """The reduced stiffness matrix is singular: some part of the solid is not held."""


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

    Raises:
        SingularStiffnessError: the LU factorisation found an exactly singular matrix.
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
        hierarchy = pyamg.smoothed_aggregation_solver(
            k if k.format == "bsr" else k.tocsr(),
            B=near_null_space,
            symmetry="symmetric",
            improve_candidates=None,  # the rigid-body modes are exact: no need to smooth them
            # Gershgorin row weights instead of a spectral-radius estimate: deterministic (the
            # estimate starts from np.random) and no threaded BLAS, for ~10% more iterations.
            smooth=("jacobi", {"weighting": "local"}),
            # one forward sweep before, one backward after: a symmetric V-cycle, as CG needs,
            # at half the cost of symmetric sweeps for ~25% more iterations (bench_fem).
            presmoother=("block_gauss_seidel", {"sweep": "forward"}),
            postsmoother=("block_gauss_seidel", {"sweep": "backward"}),
        )

        def solve(f: np.ndarray) -> np.ndarray:
            cycle = partial(v_cycle, hierarchy)
            return np.stack([conjugate_gradients(k, b, cycle) for b in f.T], axis=1)

        return solve
    raise ValueError(f"unknown method {method!r} (use 'direct', 'amg' or 'auto')")


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


def conjugate_gradients(
    a: sp.sparray | sp.spmatrix, b: np.ndarray, precondition: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray:
    """Preconditioned CG for SPD ``a`` (n, n) until ||b - a x|| <= AMG_TOLERANCE ||b||.

    Hand-written rather than pyamg's or scipy's so that no step calls multithreaded BLAS: on a
    busy 2-core machine a threaded dot product of 1e5 numbers took 5 ms instead of 0.02 ms.
    Stops quietly after :data:`AMG_MAX_ITERATIONS`; the caller checks the residual.
    """
    x = np.zeros_like(b)
    r = b.copy()
    z = precondition(r)
    p = z.copy()
    rz = _dot(r, z)
    stop = AMG_TOLERANCE * np.sqrt(_dot(b, b))
    for _ in range(AMG_MAX_ITERATIONS):
        q = a @ p
        alpha = rz / _dot(p, q)
        x += alpha * p
        r -= alpha * q
        if np.sqrt(_dot(r, r)) <= stop:
            break
        z = precondition(r)
        rz, rz_old = _dot(r, z), rz
        p *= rz / rz_old
        p += z
    return x


def _dot(u: np.ndarray, v: np.ndarray) -> float:
    """u . v without BLAS (see :func:`conjugate_gradients`)."""
    return float(np.einsum("i,i->", u, v))
