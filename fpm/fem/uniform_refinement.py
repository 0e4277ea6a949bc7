"""One uniform 1-to-8 refinement of a hexahedral mesh (the meshes of a refined reference,
:mod:`fpm.fem.refine`; a tetrahedral mesh's is :meth:`fpm.model.tetrahedra.TetMesh.refine`).

A hexahedron is split into 8 by its own trilinear map. New nodes at the middle of every edge,
face and hexahedron are shared by neighbours and come after the coarse mesh's, so the lattice's
nodes keep their numbers in a refined voxel mesh; a new node is held when the coarse nodes
spanning it are. Volume is conserved exactly, and every child is positive
(tests/core/test_refine.py).

Units: m.
"""

from __future__ import annotations

import numpy as np

from ..model.hexahedron import NATURAL

__all__ = ["refine_hexahedra"]

# ------------------------------------------------------------------ refinement

_LOCAL = np.array([(i, j, k) for k in (-1, 0, 1) for j in (-1, 0, 1) for i in (-1, 0, 1)])
"""(27, 3) natural coordinates of a hexahedron's nodes after a split: r fastest, then s, t."""
_CORNER = ((NATURAL + 1) // 2).astype(int)  # (8, 3) each corner's 0/1 offsets
_CHILDREN = np.array(
    [
        [(a + i) + 3 * (b + j) + 9 * (c + k) for i, j, k in _CORNER]
        for c in (0, 1)
        for b in (0, 1)
        for a in (0, 1)
    ]
)
"""(8, 8) the 27-point slots of each child's corners (:mod:`fpm.model.hexahedron` order)."""


def refine_hexahedra(
    nodes: np.ndarray, hexahedra: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One uniform 1-to-8 refinement of ``hexahedra`` (H, 8) on ``nodes`` (N, 3), m, by each
    hexahedron's trilinear map.

    Returns (M, 3) nodes (the old N first; then edge middles, face centres, hexahedron
    centres, shared by neighbours), (8H, 8) hexahedra (children of h at 8h .. 8h + 7) and (M,)
    bool fixed nodes: a new node is fixed when every corner spanning it is (``fixed`` (N,), none
    when None), so a held face stays held.
    """
    nodes = np.asarray(nodes, dtype=float)
    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    held = np.zeros(len(nodes), dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    n = len(nodes)
    slots = np.empty((len(hexahedra), 27), dtype=np.int64)
    new_nodes, new_fixed = [nodes], [held]
    count = n
    for size in (1, 2, 4, 8):
        spans = [
            (a, np.flatnonzero(np.all((NATURAL == p) | (p == 0), axis=1)))
            for a, p in enumerate(_LOCAL)
        ]
        spans = [(a, s) for a, s in spans if len(s) == size]
        if size == 1:
            for a, s in spans:
                slots[:, a] = hexahedra[:, s[0]]
            continue
        ids = np.stack([hexahedra[:, s] for _, s in spans], axis=1)  # (H, K, size)
        flat = np.sort(ids.reshape(-1, size), axis=1)
        unique, inverse = np.unique(flat, axis=0, return_inverse=True)
        inverse = inverse.ravel().reshape(len(hexahedra), len(spans))
        for k, (a, _) in enumerate(spans):
            slots[:, a] = count + inverse[:, k]
        new_nodes.append(nodes[unique].mean(axis=1))
        new_fixed.append(held[unique].all(axis=1))
        count += len(unique)
    children = slots[:, _CHILDREN].reshape(-1, 8)
    return np.concatenate(new_nodes), children, np.concatenate(new_fixed)
