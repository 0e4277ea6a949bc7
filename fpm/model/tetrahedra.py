"""Tetrahedral meshes as the spec carries them (``reference.mesh``): checks, and the one mesh type
(:class:`TetMesh`: volumes, edges, boundary, where points lie in it, its 1-to-8 split) with the
barycentric coordinates it rests on (:func:`barycentric`); nodes numbered twice
(:func:`merge_coincident`) and pieces (:func:`face_pieces`; :func:`lattice_pieces`: those a
lattice joins).

NumPy and SciPy only, so that :mod:`fpm.model.checks` and the service can check a mesh without
the FEM's solvers. The 10-node element built on these tetrahedra is :mod:`fpm.fem.tet10`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
"""(6, 2) corners of a tetrahedron's edges, in the order of the 10-node element's mid-edge nodes
4-9 (VTK ``tetra10``)."""
DEGENERATE = 1e-8
"""A tetrahedron whose volume is at most this times its longest edge cubed is degenerate
(a regular tetrahedron has 0.118)."""
FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
"""(4, 3) corners of the face opposite each corner, numbered outward for a positive tetrahedron."""
TOLERANCE = 1e-9
"""Barycentric margin: a point this (relative) far outside a tetrahedron still counts as in it."""
PAIR_CHUNK = 1 << 20
"""(point, candidate) pairs tested at once in :meth:`TetMesh.locate`."""


class TetMeshError(ValueError):
    """A tetrahedral mesh that cannot carry a reference; ``element`` names the first bad one."""

    def __init__(self, message: str, element: int | None = None, field: str = "tetrahedra"):
        super().__init__(message)
        self.element = element
        self.field = field


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
        mesh = TetMesh(nodes, tets)
        volume, longest = mesh.volumes, mesh.longest_edges
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


# ------------------------------------------------------------------ the mesh and points in it


def edge_matrices(coords: np.ndarray) -> np.ndarray:
    """(K, 3, 3) the edges from corner 0 to corners 1-3 as columns, m, of tetrahedra with
    corners ``coords`` (K, 4, 3), m: the Jacobian of the map from barycentric coordinates."""
    return np.transpose(coords[:, 1:] - coords[:, :1], (0, 2, 1))


def signed_volumes(coords: np.ndarray) -> np.ndarray:
    """(K,) signed volumes, m^3, of tetrahedra with corners ``coords`` (K, 4, 3), m: positive
    when corner 3 lies on the side of face (0, 1, 2) its right-hand normal points to."""
    return np.linalg.det(edge_matrices(coords)) / 6.0


def barycentric(coords: np.ndarray, points: np.ndarray, clip: bool = False) -> np.ndarray:
    """(K, 4) barycentric coordinates of ``points`` (K, 3) in tetrahedra ``coords`` (K, 4, 3);
    ``clip``: clipped to [0, 1] and scaled to sum 1 (onto the tetrahedron, for points on it up
    to round-off or within :data:`TOLERANCE`)."""
    rest = np.linalg.solve(edge_matrices(coords), (points - coords[:, 0])[:, :, None])[:, :, 0]
    lam = np.concatenate([1 - rest.sum(axis=1, keepdims=True), rest], axis=1)
    if not clip:
        return lam
    lam = np.clip(lam, 0.0, 1.0)
    return lam / lam.sum(axis=1, keepdims=True)


def unshared_faces(faces: np.ndarray) -> np.ndarray:
    """(F,) bool: the ``faces`` (F, k) (node indices of faces of any elements) that no other row
    repeats in any order: the faces of exactly one element."""
    _, inverse, counts = np.unique(
        np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True
    )
    return counts[inverse.ravel()] == 1


@dataclass
class Location:
    """Where points lie in a tetrahedral mesh (:meth:`TetMesh.locate`).

    Attributes:
        element: (P,) the tetrahedron holding each point (or, outside, the one ``locate`` names).
        lam: (P, 4) barycentric coordinates there (each in [0, 1], summing to 1).
        distance: (P,) distance from the point to the mesh, m (0 inside; NaN outside when
            ``locate`` does not project).
        inside: (P,) bool, whether the point lies in a tetrahedron (within :data:`TOLERANCE`).
    """

    element: np.ndarray
    lam: np.ndarray
    distance: np.ndarray
    inside: np.ndarray


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh: ``nodes`` (N, 3), m (or (N, 4) barycentric coordinates, for
    :meth:`refine` without ``shortest``), and ``tets`` (T, 4) node indices (int64). What is
    derived from them (corners, volumes, edges, boundary) is computed once, on first use."""

    nodes: np.ndarray
    tets: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "nodes", np.asarray(self.nodes, dtype=float))
        object.__setattr__(self, "tets", np.asarray(self.tets, dtype=np.int64))

    @cached_property
    def coords(self) -> np.ndarray:
        """(T, 4, 3) the tetrahedra's corners, m."""
        return self.nodes[self.tets]

    @cached_property
    def volumes(self) -> np.ndarray:
        """(T,) signed volumes, m^3 (:func:`signed_volumes`)."""
        return signed_volumes(self.coords)

    @cached_property
    def longest_edges(self) -> np.ndarray:
        """(T,) each tetrahedron's longest edge, m."""
        v = self.coords
        return np.linalg.norm(v[:, EDGES[:, 1]] - v[:, EDGES[:, 0]], axis=2).max(axis=1)

    @cached_property
    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """(E, 2) the distinct edges' end nodes (lower first, ascending) and (T, 6) each
        tetrahedron's edges among them, in :data:`EDGES` order."""
        n = len(self.nodes)
        ends = np.sort(self.tets[:, EDGES].reshape(-1, 2), axis=1)
        keys, edge = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
        return np.stack([keys // n, keys % n], axis=1), edge.reshape(-1, 6)

    @cached_property
    def midpoints(self) -> np.ndarray:
        """(E, 3) the middle of each edge of :attr:`edges`, m."""
        ends = self.edges[0]
        return (self.nodes[ends[:, 0]] + self.nodes[ends[:, 1]]) / 2

    @cached_property
    def boundary(self) -> tuple[np.ndarray, np.ndarray]:
        """(F, 3) boundary triangles (faces of exactly one tetrahedron, outward for positive
        tetrahedra) and (F,) the tetrahedron each belongs to."""
        faces = self.tets[:, FACES].reshape(-1, 3)
        single = unshared_faces(faces)
        return faces[single], np.repeat(np.arange(len(self.tets)), 4)[single]

    @cached_property
    def _centroids(self) -> tuple[cKDTree, float]:
        """A tree of the tetrahedra's centroids and the largest corner-to-centroid distance, m."""
        centroid = self.coords.mean(axis=1)
        reach = float(np.linalg.norm(self.coords - centroid[:, None], axis=2).max())
        return cKDTree(centroid), reach

    def locate(
        self, points: np.ndarray, nearest: int = 8, ordered: bool = False, project: bool = True
    ) -> Location:
        """Where each of ``points`` (P, 3), m, lies: in the first tetrahedron holding it of the
        ``nearest`` nearest centroids (nearest first), else of every centroid within the
        largest reach (in the tree's order; ``ordered``: by index, the lowest first). Exact,
        vectorised over (point, candidate) pairs. A point in no tetrahedron takes the nearest
        point of the boundary triangles (:meth:`nearest_on_boundary`); without ``project``,
        the tetrahedron of the nearest centroid, ``lam`` clipped there, distance NaN."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        coords = self.coords
        n = len(points)
        tree, reach = self._centroids
        k = min(nearest, len(self.tets))
        _, near = tree.query(points, k)
        near = np.asarray(near).reshape(n, k)
        pairs = np.repeat(np.arange(n), k), near.ravel()
        found, element, lam = _first_inside(coords, points, *pairs, n)
        rest = np.flatnonzero(~found)
        if len(rest):  # every tetrahedron that could hold the point: centroid within the reach
            lists = tree.query_ball_point(points[rest], reach * (1 + 1e-9), return_sorted=ordered)
            point, item = _flat_pairs(lists)
            more, which, lam_more = _first_inside(coords, points[rest], point, item, len(rest))
            found[rest[more]] = True
            element[rest[more]] = which[more]
            lam[rest[more]] = lam_more[more]
        distance = np.zeros(n)
        outside = np.flatnonzero(~found)
        if len(outside) and project:
            e, q, d = self.nearest_on_boundary(points[outside])
            element[outside] = e
            lam[outside] = barycentric(coords[e], q)
            distance[outside] = d
        elif len(outside):
            element[outside] = near[outside, 0]
            lam[outside] = barycentric(coords[element[outside]], points[outside])
            distance[outside] = np.nan
        lam = np.clip(lam, 0.0, 1.0)  # within TOLERANCE of the tetrahedron: onto it
        lam /= lam.sum(axis=1, keepdims=True)
        return Location(element, lam, distance, found)

    def nearest_on_boundary(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For ``points`` (P, 3), m (outside the mesh, or inside: the nearest point of its
        surface either way): (P,) the tetrahedron owning the nearest boundary triangle, (P, 3)
        the nearest point, (P,) its distance, m."""
        faces, owner = self.boundary
        tri = self.nodes[faces]  # (F, 3, 3)
        centre = tri.mean(axis=1)
        reach = np.linalg.norm(tri - centre[:, None], axis=2).max()
        tree = cKDTree(centre)
        k = min(8, len(faces))
        _, near = tree.query(points, k)
        near = np.asarray(near).reshape(len(points), k)
        p = np.repeat(np.arange(len(points)), k)
        q = closest_on_triangles(points[p], *(tri[near.ravel(), i] for i in range(3)))
        estimate = np.linalg.norm(q - points[p], axis=1).reshape(-1, k).min(axis=1)
        # Any triangle nearer than the estimate has its centre within estimate + reach.
        radius = estimate + reach * (1 + 1e-9) + 1e-12
        p, f = _flat_pairs(tree.query_ball_point(points, radius, return_sorted=False))
        best_d = np.full(len(points), np.inf)
        best_f = np.zeros(len(points), dtype=np.int64)
        best_q = np.zeros((len(points), 3))
        for start in range(0, len(p), PAIR_CHUNK):
            pp, ff = p[start : start + PAIR_CHUNK], f[start : start + PAIR_CHUNK]
            qq = closest_on_triangles(points[pp], tri[ff, 0], tri[ff, 1], tri[ff, 2])
            dd = np.linalg.norm(qq - points[pp], axis=1)
            order = np.lexsort((dd, pp))  # per point, the nearest first
            pp, ff, qq, dd = pp[order], ff[order], qq[order], dd[order]
            first = np.ones(len(pp), dtype=bool)
            first[1:] = pp[1:] != pp[:-1]
            pp, ff, qq, dd = pp[first], ff[first], qq[first], dd[first]
            better = dd < best_d[pp]
            pp, ff, qq, dd = pp[better], ff[better], qq[better], dd[better]
            best_d[pp], best_f[pp], best_q[pp] = dd, ff, qq
        return owner[best_f], best_q, best_d

    def refine(
        self, fixed: np.ndarray | None = None, shortest: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One uniform 1-to-8 split (Bey's red refinement: a corner tetrahedron at each corner,
        the inner octahedron cut along a diagonal into 4).

        ``shortest``: along the octahedron's shortest diagonal (the best shaped children), each
        child turned positive; else along (01, 23), children as they fall (what a split of
        barycentric coordinates needs: the children only tile the parent, equal in volume).

        Returns (N + E, 3) nodes (the old ones first, then one per distinct edge at its middle),
        (8T, 4) tetrahedra, children of tetrahedron t at 8t .. 8t + 7, and (N + E,) bool held
        nodes: a new node is held when both ends of its edge are (``fixed`` (N,), none when
        None), so the refined mesh holds exactly the region the coarse one held.
        """
        n = len(self.nodes)
        ends, edge = self.edges
        nodes = np.concatenate([self.nodes, self.midpoints])
        held = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
        held = np.concatenate([held, held[ends[:, 0]] & held[ends[:, 1]]])
        m = n + edge  # (T, 6) mid-edge nodes, EDGES order
        x = self.tets
        corners = [
            (x[:, 0], m[:, 0], m[:, 2], m[:, 3]),
            (m[:, 0], x[:, 1], m[:, 1], m[:, 4]),
            (m[:, 2], m[:, 1], x[:, 2], m[:, 5]),
            (m[:, 3], m[:, 4], m[:, 5], x[:, 3]),
        ]
        choice = np.zeros(len(x), dtype=np.int64)
        if shortest:
            lengths = [
                np.linalg.norm(nodes[m[:, a]] - nodes[m[:, b]], axis=1) for a, b in _OCTAHEDRON
            ]
            choice = np.argmin(np.stack(lengths, axis=1), axis=1)
        inner = np.zeros((len(x), 4, 4), dtype=np.int64)
        for option, ((a, b), ring) in enumerate(_OCTAHEDRON.items()):
            rows = choice == option
            for k in range(4):
                inner[rows, k] = np.stack(
                    [m[rows, a], m[rows, b], m[rows, ring[k]], m[rows, ring[(k + 1) % 4]]], axis=1
                )
        children = np.concatenate(
            [np.stack([np.stack(c, axis=1) for c in corners], axis=1), inner], axis=1
        ).reshape(-1, 4)
        if shortest:
            flip = np.linalg.det(edge_matrices(nodes[children])) < 0
            children[flip] = children[flip][:, [0, 2, 1, 3]]
        return nodes, children, held


_OCTAHEDRON = {
    # diagonal (as mid-edge slots 0-5 of EDGES: 01, 12, 02, 03, 13, 23) -> its ring of 4
    (0, 5): (2, 3, 4, 1),
    (2, 4): (0, 3, 5, 1),
    (3, 1): (0, 2, 5, 4),
}


def _first_inside(
    coords: np.ndarray, points: np.ndarray, point: np.ndarray, element: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tests the pairs (point[k], element[k]) in order; returns per point (n,) found, the first
    element holding it, lam there."""
    found = np.zeros(n, dtype=bool)
    which = np.full(n, -1, dtype=np.int64)
    lam_out = np.zeros((n, 4))
    for start in range(0, len(point), PAIR_CHUNK):
        p, e = point[start : start + PAIR_CHUNK], element[start : start + PAIR_CHUNK]
        lam = barycentric(coords[e], points[p])
        inside = lam.min(axis=1) >= -TOLERANCE
        p, e, lam = p[inside], e[inside], lam[inside]
        new = ~found[p]
        p, e, lam = p[new], e[new], lam[new]
        _, first = np.unique(p, return_index=True)
        found[p[first]] = True
        which[p[first]] = e[first]
        lam_out[p[first]] = lam[first]
    return found, which, lam_out


def _flat_pairs(lists: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(point, item) pairs of a tree's ball query ``lists`` (P,): each point's items in turn."""
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    items = np.fromiter((i for x in lists for i in x), dtype=np.int64, count=int(counts.sum()))
    return np.repeat(np.arange(len(lists)), counts), items


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(K, 3) the point of triangle (a, b, c) nearest ``p``, all (K, 3), m (Ericson, *Real-Time
    Collision Detection* 5.1.5, by Voronoi regions, vectorised)."""
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c

    def dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", x, y)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        on_ab = a + (d1 / (d1 - d3))[:, None] * ab
        on_ac = a + (d2 / (d2 - d6))[:, None] * ac
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        on_bc = b + w_bc[:, None] * (c - b)
        total = va + vb + vc
        face = a + (vb / total)[:, None] * ab + (vc / total)[:, None] * ac
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (d6 >= 0) & (d5 <= d6),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    choices = [a, b, c, on_ab, on_ac, on_bc]
    return np.select([k[:, None] for k in conditions], choices, face)


# ------------------------------------------------------------------ nodes numbered twice, pieces


def merge_coincident(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``nodes`` (N, 3) and ``tets`` (T, 4) with nodes at the same point numbered twice joined
    (e.g. where two blocks or regions of a mesh meet, each with its own nodes): a tetrahedron's
    corner at a point is the first node there, the later copies are dropped, the other nodes
    keep their order (unused ones too). Without joining, the tetrahedra on either side share no
    face, and a FEM on them sees a crack, or two pieces, where the solid is one.

    Returns:
        the nodes, the tetrahedra renumbered, and how many nodes were dropped (0: the arrays
        as given; so too for nodes that are not (N, 3) finite coordinates or a node index out
        of range, which :func:`check_tetrahedra` names as the mesh numbers them).
    """
    nodes = np.asarray(nodes, dtype=float)
    tets = np.asarray(tets, dtype=np.int64)
    if (
        nodes.ndim != 2
        or nodes.shape[1:] != (3,)
        or not len(nodes)
        or not np.isfinite(nodes).all()
        or (tets.size and (tets.min() < 0 or tets.max() >= len(nodes)))
    ):
        return nodes, tets, 0
    _, first, same = np.unique(nodes, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(nodes):
        return nodes, tets, 0
    merged = first[same.reshape(-1)]  # each node's first one at its point
    kept = merged == np.arange(len(nodes))
    number = np.cumsum(kept) - 1  # a kept node's index among the kept
    return nodes[kept], number[merged][tets], int(len(nodes) - kept.sum())


def face_pieces(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) the piece of each tetrahedron ``tets`` (T, 4) on ``nodes`` (N, 3): tetrahedra that
    share a face (three corners at the same positions, whether or not the mesh numbers them
    as the same nodes) are in one piece; pieces numbered from 0."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, same = np.unique(nodes, axis=0, return_inverse=True)
    corners = same.reshape(-1)[tets]
    faces = np.sort(corners[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    m = int(faces.max()) + 1
    if m < 2**21:  # a face as one int64: ten times faster than unique rows (the service's submit)
        _, face = np.unique((faces[:, 0] * m + faces[:, 1]) * m + faces[:, 2], return_inverse=True)
    else:
        _, face = np.unique(faces, axis=0, return_inverse=True)
    count = len(tets) + int(face.max()) + 1
    owner = np.repeat(np.arange(len(tets)), 4)
    graph = coo_matrix(
        (np.ones(len(owner)), (owner, len(tets) + face.reshape(-1))), shape=(count, count)
    )
    return connected_components(graph, directed=False)[1][: len(tets)]


@dataclass(frozen=True)
class Pieces:
    """A tetrahedral mesh's pieces and the lattice cells each holds (:func:`lattice_pieces`).

    Attributes:
        piece: (T,) the piece of each tetrahedron (:func:`face_pieces`), numbered from 0.
        cells: (P,) how many of the lattice's cell centres each piece holds (a centre outside
            the mesh counts for the piece of its nearest boundary point, :meth:`TetMesh.locate`).
    """

    piece: np.ndarray
    cells: np.ndarray

    @property
    def held(self) -> np.ndarray:
        """(P,) bool: the pieces that hold a lattice cell."""
        return self.cells > 0

    def joined_apart(
        self, nodes: np.ndarray, tets: np.ndarray, numbering: np.ndarray | None = None
    ) -> str | None:
        """None when at most one piece holds lattice cells; else what is wrong: the lattice's
        cells are one solid where the FEM on the tetrahedra ``tets`` (T, 4) on ``nodes``
        (N, 3), m, would hold and load the pieces apart. The message names the piece holding
        the second most cells by its first tetrahedron (``numbering`` (T,): its index as the
        user numbers it; else its index in ``tets``), its size and its centre."""
        held = self.held
        if held.sum() <= 1:
            return None
        other = np.flatnonzero(held)[np.argsort(-self.cells[held], kind="stable")[1]]
        members = np.flatnonzero(self.piece == other)
        first = int(members[0] if numbering is None else numbering[members[0]])
        centre = ", ".join(f"{float(x):.4g}" for x in nodes[tets[members]].mean(axis=(0, 1)))
        return (
            f"the mesh's tetrahedra are {len(self.cells)} pieces not joined through shared "
            f"faces, and the lattice's cells join {int(held.sum())} of them into one solid: "
            f"the piece of tetrahedron {first} ({len(members)} tetrahedra, around [{centre}] m) "
            "touches or overlaps the rest without sharing faces with it, so the FEM reference "
            "on the tetrahedra would hold and load it apart: join the pieces by shared faces (a "
            "conforming mesh) or remove it (if they are apart, a finer spacing keeps their cells "
            "apart too)"
        )


def lattice_pieces(nodes: np.ndarray, tets: np.ndarray, centres: np.ndarray) -> Pieces:
    """The pieces of the tetrahedra ``tets`` (T, 4) on ``nodes`` (N, 3), m (joined through
    faces at the same positions: nodes numbered twice need no merging), and how many of a
    lattice's cell ``centres`` (C, 3), m, each holds. The lattice's cells are one solid, so
    two pieces holding cells are joined by the lattice but not by a FEM on the tetrahedra
    (:meth:`Pieces.joined_apart` says which); a piece holding none is no part of the lattice's
    solid. Only a mesh of two or more pieces locates the centres."""
    piece = face_pieces(nodes, tets)
    count = int(piece.max()) + 1
    if count == 1:
        return Pieces(piece, np.array([len(centres)]))
    cells = np.bincount(piece[TetMesh(nodes, tets).locate(centres).element], minlength=count)
    return Pieces(piece, cells)
