"""A lattice nodal force as the load it stands for: spread over that node's share of the solid.

A lattice node stands for the part of the solid around it, so a force on it is a load on that
part, not on a point: a point load's displacement in a continuum is infinite at the point and
grows without bound under refinement, so a reference that is to converge under refinement
(:mod:`fpm.fem.refine`) cannot apply it as one. A node's *share* is its *hat*, the trilinear
shape function of the lattice's cells around it,
``phi_x(p) = prod_k max(0, 1 - |p_k - x_k| / h_k)`` (1 at the node, 0 at its neighbours and
beyond, 2 h_k across; ``h_k`` the lattice's spacing along axis k, :func:`lattice_spacing`), and
each lattice nodal force ``f`` at node ``x`` becomes:

- on a node of the lattice's surface (a corner of a hexahedron face that belongs to one
  hexahedron only): a traction on the solid's surface within its hat, in proportion to the hat;
- on an interior node: a body load on the solid's volume within its hat, in proportion to it;
- where the hat holds no surface (the solid's surface runs past the node's share), its volume;
  where it holds neither, a point load at the node's place in the solid.

Why the hat and not a uniform load on the points nearest the node (a patch about h x h, which
this module spread before): the hat's load falls to zero continuously at the edge of its
support where the patch's jumps, and a refined mesh resolves it sooner. On the 480-tetrahedron
organ of ``bench refine`` at h = 3.5 mm the last change of ``refine: "auto"`` (three
refinements, 342,225 FEM nodes) fell from 1.70 / 1.34 / 2.17 / 1.55 / 2.01% to 1.47 / 1.10 /
1.74 / 1.18 / 1.66% per load case, the loaded nodes' own change from 11-28% to 10-21%.

The surface and the volume are sampled (:class:`Samples`: points no further apart than
h / :data:`SAMPLES_PER_H`, each with its area or volume), so the load is the same at every level
of refinement and only the FEM's resolution of it changes. Every sample then carries a point
load that goes to its element's nodes by their shape function values there (the consistent
load of the sampled traction: same resultant, same moment, for any element whose shape
functions reproduce a linear field).

**Resultant and moment.** The shares sum to ``f`` exactly. A load's resultant acts at the
weighted centroid of its samples, which where the hat is cut by an edge of the solid is not on
the force's line of action, so the spread force would add a couple the lattice's force has
not. The weights are therefore tilted linearly across the samples (``w_q (1 + g . (p_q - c))``,
which leaves their sum unchanged) so that their centroid moves onto the line through ``x``
along ``f``, as far as their extent allows (not off a flat surface's plane) and no weight
turns negative: on a flat surface the spread load then has the lattice force's resultant and
moment exactly (tests/test_refine.py).

Units: m, N, m^2, m^3.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..model.hexahedron import NATURAL
from ..model.tetrahedra import EDGES

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


def hexahedron_faces(hexahedra: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every face of ``hexahedra`` (H, 8): (6H, 4) corner nodes, (6H,) hexahedron, (6H,) local
    face 0-5 (``axis * 2 + (sign > 0)``: r-, r+, s-, s+, t-, t+)."""
    corners, owner, local = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            corners.append(hexahedra[:, NATURAL[:, axis] == sign])
            owner.append(np.arange(len(hexahedra)))
            local.append(np.full(len(hexahedra), 2 * axis + (sign > 0)))
    return np.concatenate(corners), np.concatenate(owner), np.concatenate(local)


def boundary_hexahedron_faces(hexahedra: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces of :func:`hexahedron_faces` on the lattice's surface
    (:func:`fpm.model.geometry.boundary_faces`: of one hexahedron only, graded interfaces
    excepted)."""
    from ..model.geometry import boundary_faces

    corners, owner, local = hexahedron_faces(hexahedra)
    single = boundary_faces(hexahedra).T.ravel()
    return corners[single], owner[single], local[single]


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


def _near(centres: np.ndarray, radius: np.ndarray, loaded: np.ndarray, reach: float) -> np.ndarray:
    """(E,) bool: elements whose centre lies within ``reach`` + their radius of a loaded point."""
    if len(loaded) == 0 or len(centres) == 0:
        return np.zeros(len(centres), dtype=bool)
    distance, _ = cKDTree(loaded).query(centres)
    return np.asarray(distance <= reach + radius)


def _trilinear(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    centre = coords.mean(axis=1)
    radius = np.linalg.norm(coords - centre[:, None], axis=2).max(axis=1)
    keep = _near(centre, radius, loaded, SURFACE_REACH * h)
    if not keep.any():
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
        shape, grad = _trilinear(xi)  # (S, 8), (S, 8, 3)
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
    return _concatenate(out, 3)


def hexahedron_volume_samples(
    nodes: np.ndarray, hexahedra: np.ndarray, loaded: np.ndarray, h: float
) -> Samples:
    """Samples of the hexahedra within :data:`VOLUME_REACH` h of the ``loaded`` points:
    n^3 cell centres each, weighted by their volume (det J times the cell's natural volume)."""
    coords = nodes[hexahedra]
    centre = coords.mean(axis=1)
    radius = np.linalg.norm(coords - centre[:, None], axis=2).max(axis=1)
    keep = np.flatnonzero(_near(centre, radius, loaded, VOLUME_REACH * h))
    if not len(keep):
        return Samples.empty(3)
    coords = coords[keep]
    longest = float(np.linalg.norm(coords[:, 6] - coords[:, 0], axis=1).max())
    n = min(2**MAX_VOLUME_LEVELS, subdivisions(longest, h))
    c = _centres_1d(n)
    xi = np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3)
    shape, grad = _trilinear(xi)
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
    for _ in range(levels):
        nodes, tets = _split_barycentric(nodes, tets)
    lam = np.einsum("pk,tkd->tpd", TETRAHEDRON_POINTS, nodes[tets]).reshape(-1, 4)
    return lam, np.full(len(lam), 1.0 / (4 * len(tets)))


def _split_barycentric(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-to-8 split in barycentric space (no orientation or diagonal choice: the children only
    have to tile the parent with equal volumes, which any of the three diagonals gives)."""
    n = len(nodes)
    ends = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    keys, edge = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
    mid = (nodes[keys // n] + nodes[keys % n]) / 2
    m = n + edge.reshape(-1, 6)
    x = tets
    e01, e12, e02, e03, e13, e23 = (m[:, k] for k in range(6))
    children = [
        (x[:, 0], e01, e02, e03),
        (e01, x[:, 1], e12, e13),
        (e02, e12, x[:, 2], e23),
        (e03, e13, e23, x[:, 3]),
        (e01, e23, e02, e03),
        (e01, e23, e03, e13),
        (e01, e23, e13, e12),
        (e01, e23, e12, e02),
    ]
    out = np.stack([np.stack(c, axis=1) for c in children], axis=1).reshape(-1, 4)
    return np.concatenate([nodes, mid]), out


def tetrahedron_surface_samples(
    nodes: np.ndarray,
    tets: np.ndarray,
    faces: np.ndarray,
    owner: np.ndarray,
    loaded: np.ndarray,
    h: float,
) -> Samples:
    """Samples of the boundary triangles ``faces`` (F, 3) (of tetrahedra ``owner`` (F,)) within
    :data:`SURFACE_REACH` h of the ``loaded`` points: the centroids of n^2 equal sub-triangles
    each, weighted by their area; ``local`` is barycentric in the owning tetrahedron."""
    tri = nodes[faces]  # (F, 3, 3)
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    keep = np.flatnonzero(_near(centre, radius, loaded, SURFACE_REACH * h))
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
        barycentric(nodes[tets[element]], points),
    )


def tetrahedron_volume_samples(
    nodes: np.ndarray, tets: np.ndarray, loaded: np.ndarray, h: float
) -> Samples:
    """Samples of the tetrahedra within :data:`VOLUME_REACH` h of the ``loaded`` points: the
    centroids of their children after enough uniform refinements, weighted by their volume."""
    coords = nodes[tets]
    centre = coords.mean(axis=1)
    radius = np.linalg.norm(coords - centre[:, None], axis=2).max(axis=1)
    keep = np.flatnonzero(_near(centre, radius, loaded, VOLUME_REACH * h))
    if not len(keep):
        return Samples.empty(4)
    coords = coords[keep]
    longest = float(np.linalg.norm(coords[:, EDGES[:, 0]] - coords[:, EDGES[:, 1]], axis=2).max())
    levels = min(MAX_VOLUME_LEVELS, max(0, math.ceil(math.log2(subdivisions(longest, h)) - 1e-9)))
    lam, share = tetrahedron_rule(levels)
    volume = np.abs(np.linalg.det(np.transpose(coords[:, 1:] - coords[:, :1], (0, 2, 1)))) / 6
    points = np.einsum("sk,wkd->wsd", lam, coords).reshape(-1, 3)
    return Samples(
        points,
        (volume[:, None] * share[None]).ravel(),
        np.repeat(keep, len(lam)),
        np.tile(lam, (len(keep), 1)),
    )


def barycentric(coords: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 4) barycentric coordinates of ``points`` (K, 3) in tetrahedra ``coords`` (K, 4, 3),
    clipped onto the tetrahedron (samples lie on it up to round-off)."""
    edges = np.transpose(coords[:, 1:] - coords[:, :1], (0, 2, 1))
    rest = np.linalg.solve(edges, (points - coords[:, 0])[:, :, None])[:, :, 0]
    lam = np.clip(np.concatenate([1 - rest.sum(axis=1, keepdims=True), rest], axis=1), 0, 1)
    return lam / lam.sum(axis=1, keepdims=True)


def _concatenate(parts: list[Samples], width: int) -> Samples:
    if not parts:
        return Samples.empty(width)
    return Samples(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.weights for p in parts]),
        np.concatenate([p.element for p in parts]),
        np.concatenate([p.local for p in parts]),
    )


@dataclass
class Spread:
    """Point loads at samples equivalent to the lattice's nodal forces (:func:`spread`).

    Attributes:
        samples: the samples that carry load (surface, then volume, then fallback points).
        forces: (L, Q, 3) the load on each sample per load case, N.
        kinds: per loaded lattice node, how it was spread: ``"traction"``, ``"body"`` or
            ``"point"`` (keyed by node index).
    """

    samples: Samples
    forces: np.ndarray
    kinds: dict[int, str]


def spread(
    lattice: np.ndarray,
    surface: np.ndarray,
    spacing: np.ndarray,
    forces: np.ndarray,
    on_surface: Samples,
    in_volume: Callable[[], Samples],
    at_nodes: Samples,
) -> Spread:
    """Spread the lattice's nodal ``forces`` (L, N, 3), N, over the nodes' hats (module
    docstring).

    Args:
        lattice: (N, 3) lattice node positions, m.
        surface: (N,) bool, the lattice's surface nodes (:func:`lattice_surface`).
        spacing: (3,) the lattice's spacing along each axis (:func:`lattice_spacing`), m.
        forces: (L, N, 3) nodal forces per load case, N.
        on_surface: samples of the solid's surface near the loaded nodes.
        in_volume: makes the samples of the solid's volume near the loaded nodes (called only
            when an interior node is loaded, or a surface node's hat holds no surface).
        at_nodes: (N) one sample per lattice node: where it lies in the solid (the fallback
            point load).
    """
    loaded = np.flatnonzero(np.any(forces != 0, axis=(0, 2)))
    n_cases = len(forces)
    volume: list[Samples] = []  # made on first need

    def share(node: int) -> tuple[Samples, str]:
        if surface[node] and (chosen := _under_hat(on_surface, lattice[node], spacing)) is not None:
            return chosen, "traction"
        if not volume:
            volume.append(in_volume())
        if (chosen := _under_hat(volume[0], lattice[node], spacing)) is not None:
            return chosen, "body"
        return at_nodes.take(np.array([node])), "point"

    pieces: list[Samples] = []
    loads: list[np.ndarray] = []
    kinds: dict[int, str] = {}
    for node in (int(i) for i in loaded):
        chosen, kinds[node] = share(node)
        on_samples = np.zeros((n_cases, len(chosen), 3))
        for case in range(n_cases):
            f = forces[case, node]
            if np.any(f != 0):
                on_samples[case] = (
                    tilted_weights(chosen.points, chosen.weights, lattice[node], f)[:, None]
                    * f[None, :]
                )
        pieces.append(chosen)
        loads.append(on_samples)
    width = at_nodes.local.shape[1]
    samples = _concatenate(pieces, width)
    out = np.concatenate(loads, axis=1) if loads else np.zeros((n_cases, 0, 3))
    return Spread(samples, out, kinds)


def hat(points: np.ndarray, node: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(Q,) the lattice node's hat at ``points`` (Q, 3): the trilinear shape function of the
    lattice's cells around ``node`` (3,), ``spacing`` (3,) m apart (module docstring)."""
    return np.prod(np.clip(1.0 - np.abs(points - node) / spacing, 0.0, None), axis=1)


def _under_hat(samples: Samples, node: np.ndarray, spacing: np.ndarray) -> Samples | None:
    """The ``samples`` within ``node``'s hat, each weight times the hat there (None: none)."""
    values = hat(samples.points, node, spacing)
    inside = np.flatnonzero(values > 0)
    if not len(inside) or values[inside] @ samples.weights[inside] <= 0:
        return None
    chosen = samples.take(inside)
    return Samples(chosen.points, chosen.weights * values[inside], chosen.element, chosen.local)


def tilted_weights(
    points: np.ndarray, weights: np.ndarray, node: np.ndarray, force: np.ndarray
) -> np.ndarray:
    """(Q,) shares of ``force`` on the samples (``points`` (Q, 3) with ``weights`` (Q,)), summing
    to 1: the weights, tilted linearly so that their centroid lies on the line through ``node``
    along ``force`` where the samples' extent allows it, none negative (module docstring)."""
    total = weights.sum()
    if len(points) == 1 or total <= 0:
        return np.full(len(points), 1.0 / len(points))
    w = weights / total
    centroid = w @ points
    direction = force / np.linalg.norm(force)
    target = node + ((centroid - node) @ direction) * direction
    d = points - centroid
    second = (w[:, None] * d).T @ d  # (3, 3) second moment about the centroid
    values, vectors = np.linalg.eigh(second)
    scale = values.max()
    if scale <= 0:
        return w
    keep = values > 1e-6 * scale
    shift = vectors[:, keep].T @ (target - centroid)
    g = vectors[:, keep] @ (shift / values[keep])  # sum w (1 + g.d) d = second @ g = target - c
    tilt = d @ g
    lowest = tilt.min()
    if lowest < -1:  # would turn a weight negative: go as far as it allows
        tilt *= -1 / lowest
    out = w * (1 + tilt)
    return out / out.sum()


def tetrahedron_nodal_loads(
    elements: np.ndarray, n_nodes: int, samples: Samples, forces: np.ndarray
) -> np.ndarray:
    """(L, M, 3) consistent nodal forces of point loads ``forces`` (L, Q, 3) at ``samples``
    (barycentric ``local``) on 10-node tetrahedra ``elements`` (T, 10) of ``n_nodes`` nodes."""
    lam = samples.local
    corner = lam * (2 * lam - 1)
    edge = 4 * lam[:, EDGES[:, 0]] * lam[:, EDGES[:, 1]]
    weights = np.concatenate([corner, edge], axis=1)  # (Q, 10)
    return _scatter(elements[samples.element], weights, forces, n_nodes)


def hexahedron_nodal_loads(
    hexahedra: np.ndarray, n_nodes: int, samples: Samples, forces: np.ndarray
) -> np.ndarray:
    """(L, M, 3) consistent nodal forces of point loads ``forces`` (L, Q, 3) at ``samples``
    (natural ``local``) on 8-node hexahedra (H, 8) of ``n_nodes`` nodes."""
    weights, _ = _trilinear(samples.local)  # (Q, 8)
    return _scatter(hexahedra[samples.element], weights, forces, n_nodes)


def _scatter(
    nodes: np.ndarray, weights: np.ndarray, forces: np.ndarray, n_nodes: int
) -> np.ndarray:
    """Sum ``forces`` (L, Q, 3) times ``weights`` (Q, k) onto ``nodes`` (Q, k)."""
    out = np.zeros((len(forces), n_nodes, 3))
    flat = nodes.ravel()
    for case in range(len(forces)):
        for i in range(3):
            out[case, :, i] = np.bincount(
                flat, (forces[case, :, i, None] * weights).ravel(), n_nodes
            )
    return out
