"""Tetrahedral meshes as the spec carries them (``reference.mesh``): checks and volumes.

NumPy only, so that :mod:`fpm.model.problem` and the service can check a mesh without the FEM's
solvers. The 10-node element built on these tetrahedra is :mod:`fpm.fem.tet10`.
"""

from __future__ import annotations

import numpy as np

EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
"""(6, 2) corners of a tetrahedron's edges, in the order of the 10-node element's mid-edge nodes
4-9 (VTK ``tetra10``)."""
DEGENERATE = 1e-8
"""A tetrahedron whose volume is at most this times its longest edge cubed is degenerate
(a regular tetrahedron has 0.118)."""


class TetMeshError(ValueError):
    """A tetrahedral mesh that cannot carry a reference; ``element`` names the first bad one."""

    def __init__(self, message: str, element: int | None = None, field: str = "tetrahedra"):
        super().__init__(message)
        self.element = element
        self.field = field


def tetrahedron_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) signed volumes, m^3, of ``tets`` (T, 4) on ``nodes`` (N, 3), m: positive when
    corner 3 lies on the side of face (0, 1, 2) its right-hand normal points to."""
    v = nodes[tets]
    return np.linalg.det(np.transpose(v[:, 1:] - v[:, :1], (0, 2, 1))) / 6.0


def check_tetrahedra(
    nodes: np.ndarray, tets: np.ndarray, limit: int = 20
) -> list[tuple[str, int | None, str]]:
    """What is wrong with a tetrahedral mesh, as (field, index, message), at most ``limit``.

    Checks: (N, 3) finite nodes, (T, 4) tetrahedra, node indices in range and distinct, no
    inverted (negative volume) and no degenerate (volume at most :data:`DEGENERATE` times the
    longest edge cubed) tetrahedron. ``field`` is ``"nodes"`` or ``"tetrahedra"``, ``index``
    the node or element (None for the whole array). Empty: the mesh is usable.
    """
    nodes = np.asarray(nodes, dtype=float)
    tets = np.asarray(tets)
    if nodes.ndim != 2 or nodes.shape[1:] != (3,) or len(nodes) < 4:
        return [("nodes", None, "need at least 4 nodes, each [x, y, z] (m)")]
    bad = np.flatnonzero(~np.isfinite(nodes).all(axis=1))
    if len(bad):
        return [
            ("nodes", int(i), f"node {int(i)} has a non-finite coordinate") for i in bad[:limit]
        ]
    if tets.ndim != 2 or tets.shape[1:] != (4,) or len(tets) < 1:
        return [("tetrahedra", None, "need at least one tetrahedron, each 4 node indices")]
    if not np.issubdtype(tets.dtype, np.integer):
        return [("tetrahedra", None, "node indices must be integers")]
    errors: list[tuple[str, int | None, str]] = []
    n = len(nodes)
    out = np.flatnonzero((tets < 0).any(axis=1) | (tets >= n).any(axis=1))
    errors += [
        ("tetrahedra", int(e), f"tetrahedron {int(e)} names a node out of range (0..{n - 1})")
        for e in out[:limit]
    ]
    srt = np.sort(tets, axis=1)
    repeated = np.flatnonzero((srt[:, 1:] == srt[:, :-1]).any(axis=1))
    errors += [
        ("tetrahedra", int(e), f"tetrahedron {int(e)} repeats a node (needs 4 distinct nodes)")
        for e in np.setdiff1d(repeated, out)[: limit - len(errors)]
    ]
    if errors:
        return errors[:limit]
    tets = tets.astype(np.int64)
    with np.errstate(over="ignore", invalid="ignore"):
        volume = tetrahedron_volumes(nodes, tets)
        v = nodes[tets]
        longest = np.linalg.norm(v[:, EDGES[:, 1]] - v[:, EDGES[:, 0]], axis=2).max(axis=1)
        huge = ~np.isfinite(volume) | ~np.isfinite(longest**3)
    errors += [
        ("tetrahedra", int(e), f"tetrahedron {int(e)}: its coordinates are too large (m)")
        for e in np.flatnonzero(huge)[:limit]
    ]
    if errors:
        return errors
    flat = np.abs(volume) <= DEGENERATE * longest**3
    inverted = (volume < 0) & ~flat
    for e in np.flatnonzero(flat | inverted)[:limit]:
        if flat[e]:
            errors.append(
                (
                    "tetrahedra",
                    int(e),
                    f"tetrahedron {int(e)} is degenerate (volume {volume[e]:.3g} m^3, near zero "
                    f"for its longest edge {longest[e]:.3g} m): its corners are (nearly) on one "
                    "plane",
                )
            )
        else:
            errors.append(
                (
                    "tetrahedra",
                    int(e),
                    f"tetrahedron {int(e)} is inverted (negative volume {volume[e]:.3g} m^3): "
                    "swap two of its corners so corner 3 lies on the positive side of face "
                    "(0, 1, 2)",
                )
            )
    return errors


def validate_tetrahedra(nodes: np.ndarray, tets: np.ndarray) -> None:
    """Raise :class:`TetMeshError` naming the first problem :func:`check_tetrahedra` finds."""
    errors = check_tetrahedra(nodes, tets, limit=1)
    if errors:
        field, index, message = errors[0]
        raise TetMeshError(message, index, field)
