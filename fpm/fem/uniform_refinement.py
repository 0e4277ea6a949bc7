"""One uniform 1-to-8 refinement of a tetrahedral or a hexahedral mesh (the meshes of a refined
reference, :mod:`fpm.fem.refine`).

A tetrahedron is split into 8 by Bey's red refinement (a corner tetrahedron at each corner, the
inner octahedron cut along its shortest diagonal into 4), a hexahedron into 8 by its own
trilinear map. New nodes at the middle of every edge (and of every face and hexahedron) are
shared by neighbours and come after the coarse mesh's, so the lattice's nodes keep their
numbers in a refined voxel mesh; a new node is held when the coarse nodes spanning it are.
Volume is conserved exactly, and every child is positive (tests/core/test_refine.py).

Units: m.
"""

from __future__ import annotations

import numpy as np

from ..model.hexahedron import NATURAL
from ..model.tetrahedra import EDGES

__all__ = ["refine_hexahedra", "refine_tetrahedra"]

# ------------------------------------------------------------------ refinement

_OCTAHEDRON = {
    # diagonal (as mid-edge slots 0-5 of EDGES: 01, 12, 02, 03, 13, 23) -> its ring of 4
    (0, 5): (2, 3, 4, 1),
    (2, 4): (0, 3, 5, 1),
    (3, 1): (0, 2, 5, 4),
}


def refine_tetrahedra(
    nodes: np.ndarray, tets: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One uniform 1-to-8 refinement of ``tets`` (T, 4) on ``nodes`` (N, 3), m.

    Returns (N + E, 3) nodes (the old ones first, then one per distinct edge at its middle),
    (8T, 4) tetrahedra, children of tetrahedron t at 8t .. 8t + 7, all of positive volume, and
    (N + E,) bool held nodes: a new node is held when both ends of its edge are (``fixed``
    (N,), none when None), so the refined mesh holds exactly the region the coarse one held.
    """
    nodes = np.asarray(nodes, dtype=float)
    tets = np.asarray(tets, dtype=np.int64)
    n = len(nodes)
    ends = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    keys, edge = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
    mid = (nodes[keys // n] + nodes[keys % n]) / 2
    all_nodes = np.concatenate([nodes, mid])
    held = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    held = np.concatenate([held, held[keys // n] & held[keys % n]])
    m = n + edge.reshape(-1, 6)  # (T, 6) mid-edge nodes, EDGES order
    x = tets
    corners = [
        (x[:, 0], m[:, 0], m[:, 2], m[:, 3]),
        (m[:, 0], x[:, 1], m[:, 1], m[:, 4]),
        (m[:, 2], m[:, 1], x[:, 2], m[:, 5]),
        (m[:, 3], m[:, 4], m[:, 5], x[:, 3]),
    ]
    # The inner octahedron along its shortest diagonal (the best shaped children).
    lengths = np.stack(
        [np.linalg.norm(all_nodes[m[:, a]] - all_nodes[m[:, b]], axis=1) for a, b in _OCTAHEDRON],
        axis=1,
    )
    choice = np.argmin(lengths, axis=1)
    inner = np.zeros((len(tets), 4, 4), dtype=np.int64)
    for option, ((a, b), ring) in enumerate(_OCTAHEDRON.items()):
        rows = choice == option
        for k in range(4):
            inner[rows, k] = np.stack(
                [m[rows, a], m[rows, b], m[rows, ring[k]], m[rows, ring[(k + 1) % 4]]], axis=1
            )
    children = np.concatenate(
        [np.stack([np.stack(c, axis=1) for c in corners], axis=1), inner], axis=1
    ).reshape(-1, 4)
    coords = all_nodes[children]
    volume = np.linalg.det(np.transpose(coords[:, 1:] - coords[:, :1], (0, 2, 1)))
    flip = volume < 0
    children[flip] = children[flip][:, [0, 2, 1, 3]]
    return all_nodes, children, held


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
