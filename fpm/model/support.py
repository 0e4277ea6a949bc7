"""Is the solid held? The fixed nodes must stop every rigid-body motion, or K X = F has no answer.

Hexahedra that share a face move together: a face-connected block of hexahedra has exactly six
rigid-body motions, and three fixed nodes not on one line stop them. Blocks that touch only along
an edge or at a corner can still turn about that edge or corner. So a block is held when its fixed
nodes, together with the nodes it shares with blocks already held, do not all lie on one line;
this is repeated until no more blocks become held, and the solid is held when every block is.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

FACES = np.array(
    [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
)
"""(6, 4) local nodes of the faces of a hexahedron (:mod:`fpm.model.hexahedron` order)."""


def face_blocks(hexahedra: np.ndarray) -> np.ndarray:
    """(H,) block label of each hexahedron (H, 8): hexahedra sharing a face share a label."""
    faces = np.sort(hexahedra[:, FACES].reshape(-1, 4), axis=1)
    _, face_id = np.unique(faces, axis=0, return_inverse=True)
    owner = np.repeat(np.arange(len(hexahedra)), 6)
    incidence = sp.coo_matrix((np.ones(len(owner)), (owner, face_id.ravel()))).tocsr()
    _, labels = connected_components(incidence @ incidence.T, directed=False)
    return labels


def off_line(points: np.ndarray, tol: float) -> bool:
    """True when ``points`` (P, 3), m, are not all within ``tol`` of one straight line."""
    if len(points) < 3:
        return False
    x = points - points.mean(axis=0)
    direction = np.linalg.svd(x, full_matrices=False)[2][0]
    return bool(np.max(np.linalg.norm(x - np.outer(x @ direction, direction), axis=1)) > tol)


def unheld_reason(
    nodes: np.ndarray, hexahedra: np.ndarray, fixed: np.ndarray, one_block: bool = False
) -> str | None:
    """Why the solid can still move as a rigid body, in a user's words; None when it is held.

    Args:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices.
        fixed: (N,) bool, fixed nodes.
        one_block: the hexahedra are known to be face-connected (a box), so skip the search.
    """
    tol = 1e-9 * float(np.ptp(nodes, axis=0).max())
    n_fixed = int(fixed.sum())
    if n_fixed == 0:
        return (
            "the solid is not held: no node is fixed, so it can move as a rigid body. "
            "Fix at least three nodes that are not on one line (e.g. a face)."
        )
    labels = np.zeros(len(hexahedra), dtype=np.int64) if one_block else face_blocks(hexahedra)
    n_blocks = int(labels.max()) + 1
    if n_blocks == 1:
        if off_line(nodes[fixed], tol):
            return None
        if n_fixed == 1:
            return (
                "the solid is not held: only one node is fixed, so it can rotate about it. "
                "Fix at least three nodes that are not on one line (e.g. a face)."
            )
        return (
            f"the solid is not held: its {n_fixed} fixed nodes all lie on one line, so it can "
            "rotate about that line. Fix also a node off that line (e.g. fix a face)."
        )
    block_nodes = _nodes_per_block(hexahedra, labels, n_blocks)
    held_nodes = fixed.copy()
    held = np.zeros(n_blocks, dtype=bool)
    progress = True
    while progress:
        progress = False
        for b in np.flatnonzero(~held):
            own = block_nodes[b]
            if off_line(nodes[own[held_nodes[own]]], tol):
                held[b] = progress = True
                held_nodes[own] = True
    if held.all():
        return None
    loose = np.flatnonzero(~held[labels])
    return (
        f"part of the solid is not held: {len(loose)} of its {len(hexahedra)} hexahedra "
        f"(e.g. hexahedron {int(loose[0])}) are joined to the held part only along an edge or "
        "at a corner, or not at all, and have fewer than three fixed nodes off one line, so "
        "they can move as a rigid body. Join them by a face or fix some of their nodes."
    )


def _nodes_per_block(hexahedra: np.ndarray, labels: np.ndarray, n_blocks: int) -> list[np.ndarray]:
    """The unique node indices of each block."""
    pairs = np.unique(np.stack([np.repeat(labels, 8), hexahedra.ravel()], axis=1), axis=0)
    return np.split(pairs[:, 1], np.searchsorted(pairs[:, 0], np.arange(1, n_blocks)))
