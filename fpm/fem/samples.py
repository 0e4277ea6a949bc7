"""Where a spread load acts (:mod:`fpm.fem.loads`): the solid's surface and volume near the
loaded lattice nodes, sampled.

The lattice's surface is its boundary hexahedron faces (:func:`boundary_hexahedron_faces`, the
nodes on them :func:`lattice_surface`), its spacing :func:`lattice_spacing`. A reference mesh's
surface and volume near the loaded nodes are sampled (:class:`Samples`: points no further apart
than h / :data:`SAMPLES_PER_H`, each with its area or volume and its place in its element) on
hexahedra (cell centres in natural coordinates) and on tetrahedra (degree-2 rules on equal
sub-triangles and children), so the load is the same at every level of refinement and only the
FEM's resolution of it changes.

Units: m, m^2, m^3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..model.hexahedron import FACE_CORNERS, NATURAL
from ..model.tetrahedra import EDGES, TetMesh, barycentric

SAMPLES_PER_H = 8
"""Samples are at most h / this apart along every edge of a patch or a cell."""
SURFACE_REACH = 2.0
"""Surface samples are taken within this many h of a loaded node (its hat reaches sqrt(3) h)."""
VOLUME_REACH = 2.0
"""Volume samples within this many h (its hat reaches sqrt(3) h)."""
MAX_SUBDIVISION = 64
"""At most this many samples along a surface element's edge (a mesh far coarser than the
lattice)."""
MAX_VOLUME_LEVELS = 3
"""Volume samples: at most 2^this along an element's edge (4 x 8^3 = 2,048 per tetrahedron,
8^3 per hexahedron)."""


@dataclass
class Samples:
    """Points of the solid with the area or volume each stands for.

    Attributes:
        points: (Q, 3) positions, m.
        weights: (Q,) area (m^2, on the surface) or volume (m^3) each sample stands for.
        element: (Q,) the element holding each.
        local: (Q, 4) barycentric coordinates in a tetrahedron, or (Q, 3) natural coordinates
            in a hexahedron (:mod:`fpm.model.hexahedron`).
    """

    points: np.ndarray
    weights: np.ndarray
    element: np.ndarray
    local: np.ndarray

    @classmethod
    def empty(cls, width: int) -> Samples:
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, width)))

    def take(self, which: np.ndarray) -> Samples:
        return Samples(
            self.points[which], self.weights[which], self.element[which], self.local[which]
        )

    def __len__(self) -> int:
        return len(self.points)


def boundary_hexahedron_faces(hexahedra: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces of ``hexahedra`` (H, 8) on the lattice's surface
    (:func:`fpm.model.geometry.boundary_faces`: of one hexahedron only, graded interfaces
    excepted), face-major: (F, 4) corner nodes, (F,) hexahedron, (F,) local face 0-5
    (:data:`fpm.model.hexahedron.FACE_CORNERS`)."""
    from ..model.geometry import boundary_faces

    local, owner = np.nonzero(boundary_faces(hexahedra).T)
    return hexahedra[owner[:, None], FACE_CORNERS[local]], owner, local


def lattice_surface(hexahedra: np.ndarray, n_nodes: int) -> np.ndarray:
    """(N,) bool: the lattice nodes on its surface (corners of a face of one hexahedron)."""
    corners, _, _ = boundary_hexahedron_faces(hexahedra)
    surface = np.zeros(n_nodes, dtype=bool)
    surface[corners.ravel()] = True
    return surface


def lattice_spacing(nodes: np.ndarray, hexahedra: np.ndarray) -> np.ndarray:
    """(3,) the lattice's spacing along x, y, z, m: the median extent of its hexahedra (H, 8)
    on ``nodes`` (N, 3) along each axis. On a box or voxel lattice the cells' size exactly; on
    a voxel lattice whose surface nodes were moved onto a mesh's surface
    (:func:`fpm.io.meshes.conform_lattice`) the voxels' size, where its shortest spring can be
    half of it."""
    x = nodes[hexahedra]
    return np.asarray(np.median(x.max(axis=1) - x.min(axis=1), axis=0), dtype=float)


def subdivisions(longest: float, h: float) -> int:
    """Samples along an element edge of length ``longest`` so that they are at most
    h / :data:`SAMPLES_PER_H` apart."""
    return int(min(MAX_SUBDIVISION, max(1, math.ceil(longest * SAMPLES_PER_H / h - 1e-9))))


def _near(coords: np.ndarray, loaded: np.ndarray, reach: float) -> np.ndarray:
    """Indices of the elements (corners ``coords`` (E, k, 3), m) whose centre lies within
    ``reach`` + their radius (centre to farthest corner) of a ``loaded`` point (P, 3), m."""
    centres = coords.mean(axis=1)
    radius = np.linalg.norm(coords - centres[:, None], axis=2).max(axis=1)
    if len(loaded) == 0 or len(centres) == 0:
        return np.zeros(0, dtype=np.int64)
    distance, _ = cKDTree(loaded).query(centres)
    return np.flatnonzero(distance <= reach + radius)


def trilinear(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 8) trilinear shape functions and (..., 8, 3) their natural derivatives at natural
    points ``xi`` (..., 3)."""
    factors = 1 + NATURAL * xi[..., None, :]  # (..., 8, 3)
    n = np.prod(factors, axis=-1) / 8
    grad = np.empty((*factors.shape[:-1], 3))
    for a in range(3):
        b, c = [k for k in range(3) if k != a]
        grad[..., a] = NATURAL[:, a] * factors[..., b] * factors[..., c] / 8
    return n, grad


def _centres_1d(n: int) -> np.ndarray:
    """Centres of n equal parts of [-1, 1]."""
    return -1 + (2 * np.arange(n) + 1) / n


def hexahedron_surface_samples(
    nodes: np.ndarray, hexahedra: np.ndarray, loaded: np.ndarray, h: float
) -> Samples:
    """Samples of the boundary faces of ``hexahedra`` (H, 8) on ``nodes`` (M, 3) within
    :data:`SURFACE_REACH` h of the ``loaded`` points (P, 3): n x n cell centres per face in
    natural coordinates, each weighted by its area (exact on a parallelogram face)."""
    corners, owner, local = boundary_hexahedron_faces(hexahedra)
    coords = nodes[corners]  # (F, 4, 3)
    keep = _near(coords, loaded, SURFACE_REACH * h)
    if not len(keep):
        return Samples.empty(3)
    owner, local, coords = owner[keep], local[keep], coords[keep]
    longest = float(np.linalg.norm(coords - np.roll(coords, 1, axis=1), axis=2).max())
    n = subdivisions(longest, h)
    a, b = np.meshgrid(_centres_1d(n), _centres_1d(n), indexing="ij")
    a, b = a.ravel(), b.ravel()
    out = []
    for face in range(6):
        which = np.flatnonzero(local == face)
        if not len(which):
            continue
        axis, sign = divmod(face, 2)
        free = [k for k in range(3) if k != axis]
        xi = np.zeros((len(a), 3))
        xi[:, axis] = 1.0 if sign else -1.0
        xi[:, free[0]], xi[:, free[1]] = a, b
        shape, grad = trilinear(xi)  # (S, 8), (S, 8, 3)
        hex_coords = nodes[hexahedra[owner[which]]]  # (W, 8, 3)
        points = np.einsum("sn,wnd->wsd", shape, hex_coords)
        d0 = np.einsum("sn,wnd->wsd", grad[:, :, free[0]], hex_coords)
        d1 = np.einsum("sn,wnd->wsd", grad[:, :, free[1]], hex_coords)
        area = np.linalg.norm(np.cross(d0, d1), axis=2) * (2.0 / n) ** 2
        out.append(
            Samples(
                points.reshape(-1, 3),
                area.ravel(),
                np.repeat(owner[which], len(a)),
                np.tile(xi, (len(which), 1)),
            )
        )
    return concatenate(out, 3)


def hexahedron_volume_samples(
    nodes: np.ndarray, hexahedra: np.ndarray, loaded: np.ndarray, h: float
) -> Samples:
    """Samples of the hexahedra within :data:`VOLUME_REACH` h of the ``loaded`` points:
    n^3 cell centres each, weighted by their volume (det J times the cell's natural volume)."""
    coords = nodes[hexahedra]
    keep = _near(coords, loaded, VOLUME_REACH * h)
    if not len(keep):
        return Samples.empty(3)
    coords = coords[keep]
    longest = float(np.linalg.norm(coords[:, 6] - coords[:, 0], axis=1).max())
    n = min(2**MAX_VOLUME_LEVELS, subdivisions(longest, h))
    c = _centres_1d(n)
    xi = np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3)
    shape, grad = trilinear(xi)
    points = np.einsum("sn,wnd->wsd", shape, coords)
    jac = np.einsum("sna,wnd->wsad", grad, coords)
    volume = np.linalg.det(jac) * (2.0 / n) ** 3
    return Samples(
        points.reshape(-1, 3), volume.ravel(), np.repeat(keep, len(xi)), np.tile(xi, (len(keep), 1))
    )


TRIANGLE_POINTS = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
"""Barycentric points of the 3-point rule of degree 2 on a triangle (weights 1/3 each)."""
_A, _B = 0.5854101966249685, 0.1381966011250105
TETRAHEDRON_POINTS = np.array(
    [[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]]
)
"""Barycentric points of the 4-point rule of degree 2 on a tetrahedron (weights 1/4 each)."""


def triangle_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (s, t) on the triangle a + s (b - a) + t (c - a), (3 n^2, 2), and their shares of
    its area (3 n^2,): the 3-point rule of degree 2 on each of its n^2 equal sub-triangles, so a
    uniform traction times a quadratic shape function is integrated exactly."""
    corners = []
    for i in range(n):
        for j in range(n - i):
            corners.append([(i, j), (i + 1, j), (i, j + 1)])  # pointing up
            if i + j < n - 1:
                corners.append([(i + 1, j), (i + 1, j + 1), (i, j + 1)])  # pointing down
    sub = np.array(corners, dtype=float) / n  # (n^2, 3, 2)
    st = np.einsum("pk,ski->spi", TRIANGLE_POINTS, sub).reshape(-1, 2)
    return st, np.full(len(st), 1.0 / (3 * n**2))


def tetrahedron_rule(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """(4 8^levels, 4) barycentric points of the 4-point rule of degree 2 on each child of the
    tetrahedron after ``levels`` uniform 1-to-8 refinements, and their shares of its volume."""
    nodes = np.eye(4)  # barycentric coordinates as positions in R^4: refinement is affine
    tets = np.arange(4)[None]
    for _ in range(levels):  # no orientation or diagonal choice: equal children tile it
        nodes, tets, _ = TetMesh(nodes, tets).refine(shortest=False)
    lam = np.einsum("pk,tkd->tpd", TETRAHEDRON_POINTS, nodes[tets]).reshape(-1, 4)
    return lam, np.full(len(lam), 1.0 / (4 * len(tets)))


def tetrahedron_surface_samples(mesh: TetMesh, loaded: np.ndarray, h: float) -> Samples:
    """Samples of the boundary triangles of ``mesh`` within :data:`SURFACE_REACH` h of the
    ``loaded`` points (P, 3), m: the centroids of n^2 equal sub-triangles each, weighted by
    their area; ``local`` is barycentric in the owning tetrahedron."""
    faces, owner = mesh.boundary
    tri = mesh.nodes[faces]  # (F, 3, 3)
    keep = _near(tri, loaded, SURFACE_REACH * h)
    if not len(keep):
        return Samples.empty(4)
    tri, owner = tri[keep], owner[keep]
    longest = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max())
    st, share = triangle_rule(subdivisions(longest, h))
    ab, ac = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = np.linalg.norm(np.cross(ab, ac), axis=1) / 2
    points = tri[:, None, 0] + st[None, :, :1] * ab[:, None] + st[None, :, 1:] * ac[:, None]
    points = points.reshape(-1, 3)
    element = np.repeat(owner, len(st))
    return Samples(
        points,
        (area[:, None] * share[None]).ravel(),
        element,
        barycentric(mesh.coords[element], points, clip=True),  # on it up to round-off
    )


def tetrahedron_volume_samples(mesh: TetMesh, loaded: np.ndarray, h: float) -> Samples:
    """Samples of the tetrahedra of ``mesh`` within :data:`VOLUME_REACH` h of the ``loaded``
    points (P, 3), m: the centroids of their children after enough uniform refinements,
    weighted by their volume."""
    coords = mesh.coords
    keep = _near(coords, loaded, VOLUME_REACH * h)
    if not len(keep):
        return Samples.empty(4)
    coords = coords[keep]
    longest = float(np.linalg.norm(coords[:, EDGES[:, 0]] - coords[:, EDGES[:, 1]], axis=2).max())
    levels = min(MAX_VOLUME_LEVELS, max(0, math.ceil(math.log2(subdivisions(longest, h)) - 1e-9)))
    lam, share = tetrahedron_rule(levels)
    volume = np.abs(mesh.volumes[keep])
    points = np.einsum("sk,wkd->wsd", lam, coords).reshape(-1, 3)
    return Samples(
        points,
        (volume[:, None] * share[None]).ravel(),
        np.repeat(keep, len(lam)),
        np.tile(lam, (len(keep), 1)),
    )


def concatenate(parts: list[Samples], width: int) -> Samples:
    """``parts`` one after the other (none: no samples, ``local`` ``width`` wide)."""
    if not parts:
        return Samples.empty(width)
    return Samples(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.weights for p in parts]),
        np.concatenate([p.element for p in parts]),
        np.concatenate([p.local for p in parts]),
    )
