"""The global stiffness matrix K (paper Sec. 4.1, ``F = K X``) as 3x3 node blocks.

K is block-sparse: one 3x3 block per pair of nodes sharing a hexahedron. Element matrices are
computed once per distinct element shape (on a box or a voxel grid: once in all), cut into 8x8
node blocks, and summed into a BSR matrix by one sort of the node-pair keys. Unknowns are
node-major (u0, v0, w0, u1, ...), so K's block (i, j) couples node i to node j.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..model.hexahedron import GAUSS_POINTS, jacobians, shape_functions
from .elasticity import element_stiffness


def stiffness_matrix(
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    c: np.ndarray,
    integration: str = "full",
    materials: np.ndarray | None = None,
) -> sp.bsr_matrix:
    """(3N, 3N) global stiffness K, N/m, in 3x3 blocks.

    Args:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices, :mod:`fpm.model.hexahedron` order, det J > 0.
        c: (6, 6) elasticity matrix, Pa; or (M, 6, 6), one per material, with ``materials``.
        integration: ``"full"`` (2x2x2 Gauss points) or ``"selective"`` (B-bar, mean
            dilatation): :func:`fpm.fem.elasticity.element_stiffness`.
        materials: (H,) each hexahedron's index into ``c`` (M, 6, 6) (:mod:`fpm.fem.materials`).
    """
    n = len(nodes)
    shapes, which = identical_elements(nodes[hexahedra])
    if materials is None:
        ke = element_stiffness(shapes, c, integration)  # (U, 24, 24)
    else:  # one element matrix per (shape, material) present
        pairs, which = np.unique(which * len(c) + materials, return_inverse=True)
        which = which.ravel()
        ke = np.empty((len(pairs), 24, 24))
        for m in np.unique(pairs % len(c)):
            here = np.flatnonzero(pairs % len(c) == m)
            ke[here] = element_stiffness(shapes[pairs[here] // len(c)], c[m], integration)
    blocks = ke.reshape(-1, 8, 3, 8, 3).transpose(0, 1, 3, 2, 4).reshape(-1, 64, 9)
    hexahedra = hexahedra.astype(np.int64)
    keys = (np.repeat(hexahedra, 8, axis=1) * n + np.tile(hexahedra, (1, 8))).ravel()
    pairs, slot = unique_inverse(keys)
    data = np.empty((len(pairs), 9))
    for entry in range(9):  # sum the H*64 element blocks into their global blocks
        data[:, entry] = np.bincount(slot, blocks[:, :, entry][which].ravel(), len(pairs))
    indptr = np.searchsorted(pairs // n, np.arange(n + 1))
    return sp.bsr_matrix((data.reshape(-1, 3, 3), pairs % n, indptr), shape=(3 * n, 3 * n))


def body_forces(
    nodes: np.ndarray, hexahedra: np.ndarray, density: float | np.ndarray, gravity: np.ndarray
) -> np.ndarray:
    """(N, 3) consistent nodal body forces f_a = int N_a rho g dV, N, summed over hexahedra.

    2x2x2 Gauss quadrature (exact for trilinear shape functions times a trilinear det J). On a
    parallelepiped every corner gets ``rho g V_e / 8``, the lumped weight of the FPM's node
    masses; on a distorted hexahedron the shares follow the shape functions. They sum to the
    solid's weight ``rho g V``.

    Args:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices, det J > 0.
        density: rho, kg/m^3, or (H,) one per hexahedron.
        gravity: (3,) acceleration g, m/s^2.
    """
    coords = nodes[hexahedra]
    share = np.zeros(hexahedra.shape)  # (H, 8) int N_a dV, m^3
    for point in GAUSS_POINTS:
        share += shape_functions(point)[None, :] * np.linalg.det(jacobians(coords, point))[:, None]
    out = np.zeros((len(nodes), 3))
    if np.ndim(density):  # per hexahedron
        share = share * np.asarray(density, dtype=float)[:, None]
        density = 1.0
    weight = density * np.asarray(gravity, dtype=float)
    for i in range(3):
        out[:, i] = np.bincount(hexahedra.ravel(), (share * weight[i]).ravel(), len(nodes))
    return out


def unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted distinct ``keys`` (M,) int and, for each key, its index among them (M,)."""
    order = np.argsort(keys)
    ordered = keys[order]
    first = np.empty(len(keys), dtype=bool)
    first[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    slot = np.empty(len(keys), dtype=np.int64)
    slot[order] = np.cumsum(first) - 1
    return ordered[first], slot


def keep_nodes(k: sp.bsr_matrix, kept: np.ndarray) -> sp.bsr_matrix:
    """K restricted to the rows and columns of the ``kept`` (N,) bool nodes, still in blocks."""
    n = k.shape[0] // 3
    ids = sp.csr_matrix((np.arange(1, len(k.indices) + 1), k.indices, k.indptr), shape=(n, n))
    sub = ids[kept][:, kept].tocsr()
    sub.sort_indices()
    size = 3 * int(kept.sum())
    return sp.bsr_matrix((k.data[sub.data - 1], sub.indices, sub.indptr), shape=(size, size))


def identical_elements(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct hexahedron shapes up to translation.

    Args:
        coords: (H, 8, 3) node positions of each hexahedron, m.

    Returns:
        shapes (U, 8, 3) node positions relative to local node 0, m, and which (H,) shape of
        each hexahedron. Positions equal to 1e-9 of the largest hexahedron extent count as equal.
    """
    local = coords - coords[:, :1]
    grid = 1e-9 * max(float(np.abs(local).max()), np.finfo(float).tiny)
    keys = np.round(local.reshape(len(coords), 24) / grid).astype(np.int64)
    _, first, which = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return local[first], which.ravel()
