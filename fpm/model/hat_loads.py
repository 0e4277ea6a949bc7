"""A nodal force as the load it stands for (``fpm.loads: "hat"``).

The refined FEM reference (:mod:`fpm.fem.loads`) reads a force ``f`` on lattice node ``i`` as a
load on the node's share of the solid, its *hat* ``phi_i`` (the trilinear shape function of the
cells around it): a traction ``f phi_i / int phi_i dA`` on the lattice's surface for a surface
node, a body load ``f phi_i / int phi_i dV`` for an interior one. With ``loads: "node"`` (the
paper's model) the lattice takes all of ``f`` at node ``i``, a load more concentrated than the
one it is judged against: under a press the lattice dimples where the reference spreads. With
``"hat"`` the lattice takes that same distributed load as an FEM takes one, by its shape
functions (the *consistent* nodal loads):

    f_j = f * int phi_j phi_i / int phi_i        (over the surface, or the volume)

i.e. row ``i`` of the lattice's consistent mass matrix of its surface (or volume), divided by
its sum: on a flat surface 4/9 of ``f`` stays at the node, 1/9 goes to each edge neighbour,
1/36 to each diagonal one. The shares sum to 1 (the resultant is kept; the share that falls on
a held node goes to the support, as the reference's traction there does).

Why, measured on an organ: docs/explanation/organs-loads.md.

Units: m, N. Integrals by 2 x 2 (faces) and 2 x 2 x 2 (cells) Gauss points.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .geometry import boundary_faces
from .hexahedron import FACE_CORNERS, GAUSS_POINTS, shape_function_gradients, shape_functions

_GAUSS_2D = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]]) / np.sqrt(3.0)
"""(4, 2) 2 x 2 Gauss points of a face, weights 1."""


def surface_mass(nodes: np.ndarray, hexahedra: np.ndarray) -> sp.csr_matrix:
    """(N, N) ``int phi_i phi_j dA`` over the faces of ``hexahedra`` (H, 8) that belong to one
    hexahedron only (the lattice's surface), ``nodes`` (N, 3) m: m^2."""
    free = boundary_faces(hexahedra)
    rows, cols, vals = [], [], []
    for face in range(6):
        axis, side = face // 2, 2.0 * (face % 2) - 1.0
        corners = FACE_CORNERS[face]  # (4,) local nodes of the face
        cells = hexahedra[free[:, face]]
        if not len(cells):
            continue
        x = nodes[cells]  # (C, 8, 3)
        on = [a for a in range(3) if a != axis]
        mass = np.zeros((len(cells), 4, 4))
        for g in _GAUSS_2D:
            point = np.zeros(3)
            point[axis], point[on[0]], point[on[1]] = side, g[0], g[1]
            n = shape_functions(point)[corners]
            tangents = np.einsum("ka,ckb->cab", shape_function_gradients(point)[:, on], x)
            area = np.linalg.norm(np.cross(tangents[:, 0], tangents[:, 1]), axis=1)  # (C,)
            mass += area[:, None, None] * np.outer(n, n)
        ids = cells[:, corners]
        rows.append(np.repeat(ids, 4, axis=1).ravel())
        cols.append(np.tile(ids, (1, 4)).ravel())
        vals.append(mass.ravel())
    n_nodes = len(nodes)
    if not rows:
        return sp.csr_matrix((n_nodes, n_nodes))
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), (n_nodes, n_nodes)
    )


def volume_mass(nodes: np.ndarray, hexahedra: np.ndarray) -> sp.csr_matrix:
    """(N, N) ``int phi_i phi_j dV`` over ``hexahedra`` (H, 8), ``nodes`` (N, 3) m: m^3."""
    x = nodes[hexahedra]
    mass = np.zeros((len(hexahedra), 8, 8))
    for g in GAUSS_POINTS:
        n = shape_functions(g)
        jacobian = np.einsum("ka,ckb->cab", shape_function_gradients(g), x)
        mass += np.abs(np.linalg.det(jacobian))[:, None, None] * np.outer(n, n)
    rows = np.repeat(hexahedra, 8, axis=1).ravel()
    cols = np.tile(hexahedra, (1, 8)).ravel()
    return sp.csr_matrix((mass.ravel(), (rows, cols)), (len(nodes), len(nodes)))


def hat_shares(
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    loaded: np.ndarray,
    surface_masses: sp.csr_matrix | None = None,
) -> sp.csr_matrix:
    """(N, N) sparse: row i, for each node of ``loaded`` (K,), the share of a force on node i
    that each lattice node takes (module docstring: surface rows for the nodes of the surface,
    volume rows for the others; each row sums to 1); the other rows empty.
    ``surface_masses``: :func:`surface_mass` of the lattice when the caller has it."""
    loaded = np.unique(np.asarray(loaded, dtype=np.int64))
    if surface_masses is None:
        surface_masses = surface_mass(nodes, hexahedra)
    surface = surface_masses[loaded]
    inside = np.asarray(surface.sum(axis=1)).ravel() <= 0
    if inside.any():
        cells = hexahedra[np.isin(hexahedra, loaded[inside]).any(axis=1)]
        volume = volume_mass(nodes, cells)[loaded]
        surface = sp.diags(~inside * 1.0) @ surface + sp.diags(inside * 1.0) @ volume
    shares = sp.diags(1.0 / np.asarray(surface.sum(axis=1)).ravel()) @ surface
    picker = sp.csr_matrix(
        (np.ones(len(loaded)), (loaded, np.arange(len(loaded)))), (len(nodes), len(loaded))
    )
    return (picker @ shares).tocsr()


def spread_forces(
    shares: sp.csr_matrix, nodes: np.ndarray, forces: np.ndarray, fixed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The lattice's nodal loads of ``forces`` (P, 3), N, on ``nodes`` (P,): (Q,) nodes that
    take a share and are not ``fixed`` (N,) bool, ascending, and (Q, 3) their forces, N."""
    dense = np.zeros((shares.shape[0], 3))
    dense[nodes] = forces
    spread = np.asarray(shares.T @ dense)
    spread[fixed] = 0.0
    taken = np.flatnonzero(np.any(spread != 0, axis=1))
    return taken, spread[taken]
