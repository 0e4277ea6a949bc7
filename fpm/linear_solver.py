"""Solving K X = F for many load cases with one factorisation (paper Sec. 4.1, ``F = K X``).

Two methods, chosen by size (``"auto"``), measured in ``bench/bench_fem.py``:

- ``"direct"``: sparse LU (SuperLU, symmetric mode, minimum-degree ordering on K + K^T).
  Exact to round-off; its fill-in grows fast with size on 3-D meshes.
- ``"amg"``: conjugate gradients preconditioned by smoothed-aggregation algebraic multigrid
  (pyamg) built with the six rigid-body modes as near-null space, so that aggregates keep
  rotations as well as translations. Memory and time grow about linearly with size.

The factorisation (or multigrid hierarchy) is built once and reused for every load case.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pyamg
import scipy.sparse as sp
from scipy.sparse.linalg import splu

AMG_FROM_UNKNOWNS = 5_000
"""``"auto"`` uses AMG from this many unknowns on (see bench/bench_fem.py for the crossover)."""

AMG_TOLERANCE = 1e-9
"""Relative residual ||K x - f|| / ||f|| at which conjugate gradients stops."""

AMG_MAX_ITERATIONS = 1000


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
    k: sp.csr_matrix, method: str, near_null_space: np.ndarray, node_blocks: bool
) -> Callable[[np.ndarray], np.ndarray]:
    """Prepare to solve ``k`` (n, n) SPD; returns a function F (n, L) -> X (n, L).

    Args:
        k: reduced stiffness matrix, N/m.
        method: ``"direct"`` or ``"amg"``.
        near_null_space: (n, 6) rigid-body modes of the free unknowns (used by ``"amg"``).
        node_blocks: the free unknowns come in whole nodes (u, v, w), so AMG may aggregate
            3x3 blocks.

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
        a = k.tobsr(blocksize=(3, 3)) if node_blocks else k
        hierarchy = pyamg.smoothed_aggregation_solver(a, B=near_null_space, symmetry="symmetric")

        def solve(f: np.ndarray) -> np.ndarray:
            x = np.zeros_like(f, dtype=float)
            for case in range(f.shape[1]):
                x[:, case] = hierarchy.solve(
                    f[:, case], tol=AMG_TOLERANCE, accel="cg", maxiter=AMG_MAX_ITERATIONS
                )
            return x

        return solve
    raise ValueError(f"unknown method {method!r} (use 'direct', 'amg' or 'auto')")
