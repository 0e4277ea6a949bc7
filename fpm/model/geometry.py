"""From a geometry spec to arrays: nodes, hexahedra, springs, lumped masses.

A box is built with index arithmetic (a 1M-node lattice in about a second and little memory);
voxels and meshes go through their hexahedra. Both give the same springs for the same solid:
the union over hexahedra of the connectivity's local node pairs, each pair once.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np

from .hexahedron import FACE_CORNERS, GAUSS_POINTS, NATURAL, jacobians, local_families, local_pairs
from .spec import BoxGeometry, MeshGeometry, NetworkGeometry, VoxelGeometry
from .tetrahedra import unshared_faces

# A spring joins lattice offsets (dx, dy, dz) whose number of non-zero components is at most
# this, per connectivity: edges 1, face diagonals 2, body diagonals 3.
_MAX_NONZERO = {"axis": 1, "axis+face": 2, "full": 3}


@dataclass
class Solid:
    """The discretised solid.

    Attributes:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices in :mod:`fpm.model.hexahedron` order; None for a network and
            for a box until :meth:`elements` is asked (a 1M-node lattice need not hold them).
        springs: (S, 2) int32 node pairs, i < j, each pair once.
        masses: (N,) lumped node masses, kg.
        families: (S,) int8 spring family (:data:`fpm.model.hexahedron.FAMILIES`): 0 hexahedron
            edge (axis), 1 face diagonal, 2 body diagonal; all 0 for a network.
        shape: (nx, ny, nz) for a box lattice (node n = i + nx*(j + ny*k)), else None.
        levels: (H,) int8 each hexahedron's level in a graded lattice (a cell of level L is
            2^-L the size of a level-0 one: :mod:`fpm.io.meshes.graded`); None: one size.
    """

    nodes: np.ndarray
    hexahedra: np.ndarray | None
    springs: np.ndarray
    masses: np.ndarray
    families: np.ndarray
    shape: tuple[int, int, int] | None = None
    levels: np.ndarray | None = None

    def elements(self) -> np.ndarray | None:
        """(H, 8) hexahedra, built on first use for a box; None for a network."""
        if self.hexahedra is None and self.shape is not None:
            self.hexahedra = box_hexahedra(self.shape)
        return self.hexahedra


def build_solid(
    geometry: BoxGeometry | VoxelGeometry | MeshGeometry | NetworkGeometry, density: float
) -> Solid:
    """Arrays for ``geometry``; lumped mass ``density * volume / 8`` per hexahedron corner."""
    if isinstance(geometry, BoxGeometry):
        return _box(geometry, density)
    if isinstance(geometry, NetworkGeometry):
        return _network(geometry)
    if isinstance(geometry, VoxelGeometry):
        nodes, hexahedra = voxel_mesh(geometry)
    else:
        nodes = np.asarray(geometry.nodes, dtype=float)
        hexahedra = np.asarray(geometry.hexahedra, dtype=np.int64)
    springs, families = hexahedron_springs(hexahedra, geometry.connectivity)
    masses = lumped_masses(nodes, hexahedra, density)
    levels = getattr(geometry, "levels", None)
    if levels is not None and any(levels):
        return Solid(
            nodes, hexahedra, springs, masses, families, levels=np.asarray(levels, np.int8)
        )
    return Solid(nodes, hexahedra, springs, masses, families)


def box_nodes(g: BoxGeometry) -> np.ndarray:
    """(N, 3) lattice nodes, x fastest: node n = i + nx*(j + ny*k)."""
    axes = [np.linspace(o, o + s, n) for o, s, n in zip(g.origin, g.size, g.nodes, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def box_hexahedra(shape: tuple[int, int, int]) -> np.ndarray:
    """(H, 8) hexahedra of a box lattice of ``shape`` nodes, in :mod:`.hexahedron` order."""
    nx, ny, nz = shape
    k, j, i = np.meshgrid(np.arange(nz - 1), np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    base = (i + nx * (j + ny * k)).ravel()
    corner = NATURAL.astype(np.int64) > 0  # (8, 3) 0/1 offsets per local node
    offsets = corner[:, 0] + nx * (corner[:, 1] + ny * corner[:, 2])
    return base[:, None] + offsets[None, :]


def _box(g: BoxGeometry, density: float) -> Solid:
    shape = g.nodes
    nx, ny, nz = shape
    nodes = box_nodes(g)
    index = np.arange(nx * ny * nz, dtype=np.int32).reshape(nz, ny, nx)
    pairs, families = [], []
    for d in product((-1, 0, 1), repeat=3):
        # Half of the 26-neighbour stencil: the offsets whose first non-zero component is +1.
        nonzero = [c for c in d if c]
        if not nonzero or nonzero[0] < 0 or len(nonzero) > _MAX_NONZERO[g.connectivity]:
            continue
        dx, dy, dz = d
        src = index[
            max(0, -dz) : nz - max(0, dz),
            max(0, -dy) : ny - max(0, dy),
            max(0, -dx) : nx - max(0, dx),
        ]
        pairs.append(
            np.stack([src.ravel(), src.ravel() + np.int32(dx + nx * (dy + ny * dz))], axis=1)
        )
        families.append(np.full(src.size, len(nonzero) - 1, dtype=np.int8))
    springs = np.concatenate(pairs)
    springs.sort(axis=1)  # i < j; the rows need no order (the neighbour lists sort them)
    cell = np.prod(np.asarray(g.size) / (np.asarray(shape) - 1))
    # Number of cells touching a node is a product of per-axis counts (1 at an end, 2 inside).
    counts = [np.where((np.arange(n) == 0) | (np.arange(n) == n - 1), 1.0, 2.0) for n in shape]
    touching = (
        counts[2][:, None, None] * counts[1][None, :, None] * counts[0][None, None, :]
    ).ravel()
    masses = density * cell / 8.0 * touching
    return Solid(nodes, None, springs, masses, np.concatenate(families), shape=(nx, ny, nz))


def voxel_mesh(g: VoxelGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) and hexahedra (H, 8) of the occupied voxels; unused corners are dropped."""
    occ = np.asarray(g.occupancy, dtype=bool)
    cx, cy, cz = occ.shape
    shape = (cx + 1, cy + 1, cz + 1)
    # Occupancy is indexed [i][j][k]; box_hexahedra enumerates cells with i fastest.
    cells = np.transpose(occ, (2, 1, 0)).ravel()
    hexahedra = box_hexahedra(shape)[cells]
    used, hexahedra = np.unique(hexahedra, return_inverse=True)
    hexahedra = hexahedra.reshape(-1, 8)
    i = used % shape[0]
    j = (used // shape[0]) % shape[1]
    k = used // (shape[0] * shape[1])
    nodes = np.asarray(g.origin) + np.stack([i, j, k], axis=1) * np.asarray(g.spacing)
    return nodes, hexahedra


def hexahedron_springs(hexahedra: np.ndarray, connectivity: str) -> tuple[np.ndarray, np.ndarray]:
    """(S, 2) unique sorted node pairs joined by springs in ``hexahedra`` (H, 8), and (S,) their
    families (a pair that two hexahedra see as different families takes the lower one)."""
    lp = local_pairs(connectivity)
    pairs = np.stack([hexahedra[:, lp[:, 0]].ravel(), hexahedra[:, lp[:, 1]].ravel()], axis=1)
    pairs.sort(axis=1)
    family = np.tile(local_families(connectivity), len(hexahedra))
    # One int64 key per pair sorts as the pairs do (lexicographically): np.unique on it is the
    # same answer as on the rows (axis=0), sooner.
    n = np.int64(int(hexahedra.max()) + 1 if hexahedra.size else 1)
    keys, inverse = np.unique(pairs[:, 0].astype(np.int64) * n + pairs[:, 1], return_inverse=True)
    springs = np.stack([keys // n, keys % n], axis=1)
    families = np.full(len(springs), 127, dtype=np.int8)
    np.minimum.at(families, inverse.ravel(), family)
    return springs.astype(np.int32), families


def hexahedron_volumes(nodes: np.ndarray, hexahedra: np.ndarray) -> np.ndarray:
    """(H,) volumes, m^3, by 2x2x2 Gauss quadrature of det J (exact for trilinear maps)."""
    x = nodes[hexahedra]  # (H, 8, 3)
    return np.sum([np.linalg.det(jacobians(x, p)) for p in GAUSS_POINTS], axis=0)


def lumped_masses(
    nodes: np.ndarray, hexahedra: np.ndarray, density: float | np.ndarray
) -> np.ndarray:
    """(N,) node masses: each hexahedron gives density * volume / 8 to each of its nodes
    (``density`` one for all, kg/m^3, or (H,) one per hexahedron)."""
    share = density * np.abs(hexahedron_volumes(nodes, hexahedra)) / 8.0
    masses = np.zeros(len(nodes))
    np.add.at(masses, hexahedra.ravel(), np.repeat(share, 8))
    return masses


def spring_lengths(nodes: np.ndarray, springs: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """(S,) rest lengths, m, of (S, 2) springs; in chunks, so a 1M-node lattice needs no
    (S, 3) temporaries."""
    out = np.empty(len(springs))
    for a in range(0, len(springs), chunk):
        s = springs[a : a + chunk]
        d = nodes[s[:, 1]] - nodes[s[:, 0]]
        out[a : a + chunk] = np.sqrt(np.einsum("ij,ij->i", d, d))
    return out


def _network(g: NetworkGeometry) -> Solid:
    nodes = np.asarray(g.nodes, dtype=float)
    springs = np.asarray(g.springs, dtype=np.int64)
    springs.sort(axis=1)
    springs = np.unique(springs, axis=0).astype(np.int32)
    m = g.masses
    masses = np.asarray(m, dtype=float) if isinstance(m, list) else np.full(len(nodes), float(m))
    return Solid(nodes, None, springs, masses, np.zeros(len(springs), dtype=np.int8))


# --------------------------------------------------- parts of a lattice one cell thick
# Parts of a lattice one cell thick: where a spacing is too coarse for the organ.
#
# A lattice cell (8-node hexahedron) is *thin* when both of its faces across one of its local
# axes (r-/r+, s-/s+ or t-/t+: :data:`fpm.model.hexahedron.NATURAL`) lie on the lattice's surface:
# the solid is a single cell across there. One such cell alone is the staircase's bump at a tip of
# the organ (the bench's organ has 1-6 of them in a group at every spacing from 10 to 2.5 mm);
# :data:`THIN_PART_CELLS` or more of them joined together are a sheet or a rod of the solid one
# cell thick (a thin flap, a lobe's edge), which the lattice cannot bend (one layer of cells has
# no through-thickness gradient) and which the surface-conforming lattice
# (:func:`fpm.io.meshes.conform_lattice`) squashes onto both its faces at once. ``spec from-mesh``
# refines such parts (:mod:`fpm.io.meshes.graded`); what remains at the finest level is named in
# the result's warnings (:func:`fpm.model.checks.thin_part_warnings`).
#
# NumPy and SciPy only (the service checks specs with it).

THIN_PART_CELLS = 8
"""A group of at least this many thin cells sharing nodes is a part one cell thick."""


def boundary_faces(hexahedra: np.ndarray) -> np.ndarray:
    """(H, 6) bool: whether each local face (``2 * axis + (side > 0)``: r-, r+, s-, s+, t-, t+)
    of ``hexahedra`` (H, 8) is on the lattice's surface: it belongs to that hexahedron only and
    is not one side of a graded interface (:func:`graded_interfaces`)."""
    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    faces = hexahedra[:, FACE_CORNERS].transpose(1, 0, 2).reshape(-1, 4)  # (6H, 4), face-major
    single = unshared_faces(faces)
    single[graded_interfaces(hexahedra, np.flatnonzero(single))] = False
    return single.reshape(6, len(hexahedra)).T


def graded_interfaces(hexahedra: np.ndarray, unmatched: np.ndarray) -> np.ndarray:
    """Of the faces ``unmatched`` (indices into the face-major (6H,) faces of ``hexahedra``
    (H, 8), each a face of one hexahedron only), those where a cell of a graded lattice meets
    four cells of half its size: a coarse face (a, b, c, d) and the four fine faces that
    cover it, each the quarter with one of its corners and its centre node m, so that (a, m),
    (b, m), (c, m) and (d, m) are diagonals of unmatched faces. Found on the node graph alone
    (a lattice whose nodes were moved onto a surface keeps its interfaces); a lattice of one
    cell size has none (no node is a face diagonal away from all four corners of a face)."""
    unmatched = np.asarray(unmatched, dtype=np.int64)
    if len(unmatched) < 5:
        return np.zeros(0, dtype=np.int64)
    corners = np.concatenate(  # (6H, 4) face-major, each face's corners in cyclic order
        [hexahedra[:, _cycle(axis, side)] for axis in range(3) for side in (-1.0, 1.0)]
    )[unmatched]
    # A face's diagonals, its corners in cyclic order: (0, 2) and (1, 3).
    ends = np.concatenate(
        [corners[:, [0, 2]], corners[:, [2, 0]], corners[:, [1, 3]], corners[:, [3, 1]]]
    )  # (4U, 2): (node, its diagonal partner)
    owner = np.tile(np.arange(len(unmatched)), 4)
    order = np.argsort(ends[:, 0], kind="stable")
    ends, owner = ends[order], owner[order]
    # For every face f and each of its corners c, every node m that c is a diagonal away from
    # (through another unmatched face): (f, m) seen from all four corners makes m f's centre.
    face = np.repeat(np.arange(len(unmatched)), 4)
    corner = corners.ravel()
    lo = np.searchsorted(ends[:, 0], corner, side="left")
    hi = np.searchsorted(ends[:, 0], corner, side="right")
    degree = hi - lo
    rows = np.repeat(np.arange(len(corner)), degree)
    at = np.arange(int(degree.sum())) - np.repeat(np.cumsum(degree) - degree, degree) + lo[rows]
    f, c, m, fine = face[rows], corner[rows], ends[at, 1], owner[at]
    keep = fine != f
    f, c, m, fine = f[keep], c[keep], m[keep], fine[keep]
    n = np.int64(int(hexahedra.max()) + 1)
    key = f.astype(np.int64) * n + m
    # Count each (f, m) once per corner: a corner may reach m through two faces.
    _, first = np.unique(np.stack([key, c]), axis=1, return_index=True)
    _, inverse, counts = np.unique(key[first], return_inverse=True, return_counts=True)
    centre = np.isin(key, key[first][counts[inverse] == 4])
    covered = centre
    if not covered.any():
        return np.zeros(0, dtype=np.int64)
    inner = np.union1d(f[covered], fine[covered])
    return unmatched[inner]


def _cycle(axis: int, side: float) -> np.ndarray:
    """(4,) the local nodes of a hexahedron's face (``axis``, ``side``) in cyclic order."""
    on = np.flatnonzero(NATURAL[:, axis] == side)
    u, v = (NATURAL[on][:, b] for b in range(3) if b != axis)
    return on[np.argsort(np.arctan2(v, u))]


def thin_cells(hexahedra: np.ndarray) -> np.ndarray:
    """(H,) bool: the cells of ``hexahedra`` (H, 8) with both faces across one local axis on
    the surface (the solid is one cell thick there)."""
    free = boundary_faces(hexahedra)
    return (free[:, 0::2] & free[:, 1::2]).any(axis=1)


def thin_parts(hexahedra: np.ndarray) -> list[np.ndarray]:
    """The parts one cell thick of the lattice ``hexahedra`` (H, 8): groups of thin cells
    (:func:`thin_cells`) joined through shared nodes, of at least :data:`THIN_PART_CELLS` cells;
    each an ascending array of cell indices, the largest group first."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    thin = np.flatnonzero(thin_cells(hexahedra))
    if len(thin) < THIN_PART_CELLS:
        return []
    n_nodes = int(hexahedra.max()) + 1
    rows = np.repeat(np.arange(len(thin)), 8)
    graph = coo_matrix(
        (np.ones(len(rows)), (rows, len(thin) + hexahedra[thin].ravel())),
        shape=(len(thin) + n_nodes, len(thin) + n_nodes),
    )
    labels = connected_components(graph, directed=False)[1][: len(thin)]
    sizes = np.bincount(labels)
    big = [g for g in np.argsort(-sizes, kind="stable") if sizes[g] >= THIN_PART_CELLS]
    return [thin[labels == g] for g in big]


# ------------------------------------------------------------- a point of the lattice's surface

SURFACE_CANDIDATES = 24
""":func:`surface_point` projects onto this many boundary faces nearest the point (by their
centres) and keeps the closest projection."""


@dataclass
class SurfacePoint:
    """Where a point of the solid's surface falls on the lattice's surface.

    Attributes:
        nodes: (4,) the lattice nodes of the surface cell face it falls on.
        weights: (4,) their trilinear shape functions there (>= 0, sum 1).
        point: (3,) the nearest point of the lattice's surface, m (the weights' centroid).
        distance: from the given point to it, m.
        cell: the hexahedron whose face it is.
    """

    nodes: np.ndarray
    weights: np.ndarray
    point: np.ndarray
    distance: float
    cell: int


def surface_point(nodes: np.ndarray, hexahedra: np.ndarray, p: np.ndarray) -> SurfacePoint:
    """The nearest point of the lattice's surface to ``p`` (3,), m, and the shape functions of
    the face it falls on there.

    The lattice is ``hexahedra`` (H, 8) on ``nodes`` (N, 3); its surface, the faces of one
    hexahedron only (:func:`boundary_faces`), each a bilinear patch
    ``x(u, v) = sum_a N_a(xi) x_a`` of its hexahedron's trilinear shape functions
    (:func:`fpm.model.hexahedron.shape_functions`) with the face's natural coordinate held at
    +-1. The nearest point of each of the :data:`SURFACE_CANDIDATES` faces nearest ``p`` is
    found by Gauss-Newton in (u, v), clamped to the face; the closest wins. The weights are
    the 8 shape functions there, which vanish off the face, so 4 remain: they sum to 1 and
    reproduce the point (``weights @ nodes[face] == point``, linear precision), and a point
    at a node gives that node alone.
    """
    from .hexahedron import shape_function_gradients, shape_functions

    nodes = np.asarray(nodes, dtype=float)
    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    p = np.asarray(p, dtype=float)
    free = boundary_faces(hexahedra)  # (H, 6)
    cell, face = np.nonzero(free)
    axis, side = face // 2, np.where(face % 2 == 1, 1.0, -1.0)
    coords = nodes[hexahedra[cell]]  # (F, 8, 3)
    on_face = NATURAL[:, axis].T == side[:, None]  # (F, 8): the face's 4 corners
    centre = (coords * on_face[:, :, None]).sum(axis=1) / 4
    k = min(SURFACE_CANDIDATES, len(cell))
    near = np.argpartition(np.linalg.norm(centre - p, axis=1), k - 1)[:k]
    best: SurfacePoint | None = None
    for f in near:
        a, s, x = int(axis[f]), float(side[f]), coords[f]
        others = [b for b in range(3) if b != a]
        xi = np.zeros(3)
        xi[a] = s
        for _ in range(20):
            r = shape_functions(xi) @ x - p
            jac = (shape_function_gradients(xi).T @ x)[others].T  # (3, 2): dx / d(u, v)
            step = np.linalg.lstsq(jac, -r, rcond=None)[0]
            xi[others] = np.clip(xi[others] + step, -1.0, 1.0)
            if np.abs(step).max() < 1e-12:
                break
        weights = shape_functions(xi)
        at = weights @ x
        distance = float(np.linalg.norm(at - p))
        if best is None or distance < best.distance:
            corners = FACE_CORNERS[face[f]]
            w = np.where(weights[corners] > 1e-12, weights[corners], 0.0)  # rounding's crumbs
            best = SurfacePoint(
                hexahedra[cell[f], corners], w / w.sum(), at, distance, int(cell[f])
            )
    assert best is not None
    return best
