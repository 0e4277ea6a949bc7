"""A verification element: the 27-node triquadratic hexahedron, on the linear FEM's grid.

Not used by calibrations. It measures how far the 8-node reference is from a much better
element on the same mesh (volumetric locking near nu = 1/2: docs/physics.md, *The FEM
reference*): every 8-node hexahedron becomes one 27-node hexahedron with nodes at its mid-edges,
face centres and centre (placed by the hexahedron's own trilinear map, so the geometry is
unchanged), integrated with 3x3x3 Gauss points. Triquadratic elements at full integration are
free of volumetric locking at these Poisson's ratios in practice, and converge a full order
faster than trilinear ones.

Local node order (not VTK's): node ``(i + 1) + 3 (j + 1) + 9 (k + 1)`` sits at natural
coordinates ``(i, j, k)``, each in {-1, 0, 1}. Unknowns are node-major, as in the linear FEM.
Supports: a new node is fixed when every hexahedron corner spanning it (the two ends of its
edge, the four corners of its face) is fixed, so a fixed face stays fixed. Loads: nodal forces
stay on the corner nodes they act on.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
import scipy.sparse as sp

from ..model.hexahedron import NATURAL, shape_function_gradients, shape_functions
from .assembly import identical_elements
from .elasticity import strain_displacement
from .linear_solver import factorize, rigid_body_modes

LOCAL = np.array(list(product((-1, 0, 1), repeat=3)), dtype=float)[:, ::-1]
"""(27, 3) natural coordinates of the local nodes: r fastest, then s, then t."""

_POINTS_1D = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_WEIGHTS_1D = np.array([5.0, 8.0, 5.0]) / 9.0
GAUSS_27 = np.array(list(product(_POINTS_1D, repeat=3)))
"""(27, 3) 3x3x3 Gauss-Legendre points (exact for the triquadratic stiffness of a box)."""
GAUSS_27_WEIGHTS = np.prod(np.array(list(product(_WEIGHTS_1D, repeat=3))), axis=1)
"""(27,) their weights (sum 8)."""


def _lagrange(x: np.ndarray, node: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-D quadratic Lagrange polynomials of nodes -1, 0, 1 (picked by ``node``) and their
    derivatives at ``x`` (broadcast)."""
    value = np.where(node < 0, x * (x - 1) / 2, np.where(node > 0, x * (x + 1) / 2, 1 - x * x))
    slope = np.where(node < 0, x - 0.5, np.where(node > 0, x + 0.5, -2 * x))
    return value, slope


def quadratic_shape_functions(point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(27,) N_a and (27, 3) dN_a/d(r, s, t) at natural ``point`` (3,)."""
    values, slopes = _lagrange(np.asarray(point, dtype=float)[None, :], LOCAL)  # (27, 3)
    n = np.prod(values, axis=1)
    grad = np.empty((27, 3))
    for a in range(3):
        others = [b for b in range(3) if b != a]
        grad[:, a] = slopes[:, a] * values[:, others[0]] * values[:, others[1]]
    return n, grad


@dataclass(frozen=True)
class QuadraticMesh:
    """27-node hexahedra on an 8-node mesh.

    Attributes:
        nodes: (M, 3) node positions, m: the 8-node mesh's nodes first, in their order, so
            node i < N of this mesh is node i of the 8-node mesh.
        hexahedra: (H, 27) node indices, :data:`LOCAL` order.
        fixed: (M,) bool, fixed nodes (from the 8-node mesh's, module docstring).
    """

    nodes: np.ndarray
    hexahedra: np.ndarray
    fixed: np.ndarray


def quadratic_mesh(nodes: np.ndarray, hexahedra: np.ndarray, fixed: np.ndarray) -> QuadraticMesh:
    """The :class:`QuadraticMesh` of 8-node ``hexahedra`` (H, 8) on ``nodes`` (N, 3), m, with
    ``fixed`` (N,) bool nodes. Shared edges and faces share their new nodes."""
    # the 8-node corners spanning each local node: those matching it where it is not 0
    spans = [
        np.flatnonzero(np.all((NATURAL == p) | (p == 0), axis=1)) for p in LOCAL
    ]  # 27 lists of 1, 2, 4 or 8 local corners
    weights = np.array([shape_functions(p) for p in LOCAL])  # (27, 8) trilinear map
    index: dict[tuple[int, ...], int] = {}
    new_positions: list[np.ndarray] = []
    new_fixed: list[bool] = []
    out = np.empty((len(hexahedra), 27), dtype=np.int64)
    n = len(nodes)
    for h, corners in enumerate(hexahedra):
        for a, span in enumerate(spans):
            ids = corners[span]
            if len(ids) == 1:
                out[h, a] = ids[0]
                continue
            key = tuple(sorted(int(i) for i in ids))
            slot = index.get(key)
            if slot is None:
                slot = index[key] = n + len(new_positions)
                new_positions.append(weights[a] @ nodes[corners])
                new_fixed.append(bool(np.all(fixed[ids])))
            out[h, a] = slot
    all_nodes = np.concatenate([nodes, np.reshape(new_positions, (-1, 3))])
    return QuadraticMesh(all_nodes, out, np.concatenate([fixed, np.array(new_fixed, bool)]))


def element_stiffness_27(coords8: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(H, 81, 81) triquadratic element stiffness, N/m, 3x3x3 Gauss points, of hexahedra
    whose geometry is the trilinear map of their corners ``coords8`` (H, 8, 3), m."""
    ke = np.zeros((len(coords8), 81, 81))
    for point, weight in zip(GAUSS_27, GAUSS_27_WEIGHTS, strict=True):
        _, local_grad = quadratic_shape_functions(point)
        corner_grad = shape_function_gradients(point)
        jac = np.einsum("na,hnb->hab", corner_grad, coords8)  # dx_b / dxi_a
        grad = np.einsum("na,hba->hnb", local_grad, np.linalg.inv(jac))  # (H, 27, 3)
        det = np.linalg.det(jac)
        b = strain_displacement(grad)  # (H, 6, 81)
        ke += np.einsum("hpa,pq,hqb->hab", b, c, b, optimize=True) * (weight * det)[:, None, None]
    return ke


def stiffness_matrix_27(mesh: QuadraticMesh, coords8: np.ndarray, c: np.ndarray) -> sp.csr_matrix:
    """(3M, 3M) global stiffness of the 27-node mesh, N/m (``coords8``: the corners)."""
    shapes, which = identical_elements(coords8)
    ke = element_stiffness_27(shapes, c)[which]  # (H, 81, 81)
    dofs = (3 * mesh.hexahedra[:, :, None] + np.arange(3)).reshape(len(ke), 81)
    rows = np.repeat(dofs, 81, axis=1).ravel()
    cols = np.tile(dofs, (1, 81)).ravel()
    size = 3 * len(mesh.nodes)
    return sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(size, size))


def solve_hex27(
    nodes: np.ndarray, hexahedra: np.ndarray, fixed: np.ndarray, c: np.ndarray, forces: np.ndarray
) -> np.ndarray:
    """Displacements (L, N, 3), m, at the 8-node mesh's nodes, of the triquadratic solid.

    Args:
        nodes: (N, 3) rest positions, m; hexahedra: (H, 8), :mod:`fpm.model.hexahedron` order.
        fixed: (N,) bool fixed nodes.
        c: (6, 6) elasticity matrix, Pa.
        forces: (L, N, 3) nodal forces on the 8-node mesh's nodes, N.
    """
    mesh = quadratic_mesh(nodes, hexahedra, fixed)
    k = stiffness_matrix_27(mesh, nodes[hexahedra], c)
    free = np.repeat(~mesh.fixed, 3)
    f = np.zeros((len(forces), 3 * len(mesh.nodes)))
    f[:, : 3 * len(nodes)] = forces.reshape(len(forces), -1)
    kff = k[free][:, free]
    x = factorize(kff, "direct", rigid_body_modes(mesh.nodes)[free])(f[:, free].T)
    u = np.zeros_like(f)
    u[:, free] = x.T
    return u[:, : 3 * len(nodes)].reshape(forces.shape)
