"""Voxelising a solid: the lattice of spacing h (m) over a mesh, exact inside tests for
tetrahedra and closed triangle surfaces, and the lattice's pieces (see the package docstring)."""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np

from ...model.tetrahedra import edge_matrices
from ..errors import MeshError

TOLERANCE = 1e-9
"""A cell centre within this (relative) barycentric margin of a tetrahedron counts as inside it:
a centre on a face shared by two tetrahedra is never lost to rounding."""
CHUNK = 1 << 21
"""Candidate (element, cell) pairs handled at once (bounds the temporaries)."""
MAX_CELLS = 50_000_000
"""A lattice's bounding box may hold at most this many cells (a 93,718-node organ's holds about
10^5): more is a spacing or a scale in the wrong unit, refused before memory runs out."""


Planes = list[list[float]] | None
"""Per axis (x, y, z), coordinates a plane of lattice nodes should fall on (:func:`lattice`)."""


def lattice(
    lo: np.ndarray, hi: np.ndarray, spacing: float, planes: Planes = None
) -> tuple[np.ndarray, np.ndarray]:
    """(origin, cells per axis) of the lattice of ``spacing`` over the box [lo, hi]: centred on
    it with ``ceil(extent / h)`` cells per axis (at least 1), except along an axis where
    ``planes`` names coordinates (:func:`support_planes`): there the first of them strictly
    inside (lo, hi) gets a plane of lattice nodes, and the cells cover [lo, hi] from it."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    cells = np.maximum(1, np.ceil((hi - lo) / spacing - 1e-9)).astype(np.int64)
    origin = (lo + hi) / 2 - cells * spacing / 2
    for a, candidates in enumerate(planes or ()):
        inside = [c for c in candidates if lo[a] + 1e-9 * spacing < c < hi[a] - 1e-9 * spacing]
        if inside:
            below = int(np.ceil((inside[0] - lo[a]) / spacing - 1e-9))
            origin[a] = inside[0] - below * spacing
            cells[a] = below + max(1, int(np.ceil((hi[a] - inside[0]) / spacing - 1e-9)))
    if float(np.prod(cells.astype(float))) > MAX_CELLS:
        span = " x ".join(str(int(c)) for c in cells)
        raise MeshError(
            f"a lattice of spacing h = {spacing:.4g} m over the mesh's {_fmt(hi - lo)} m would "
            f"span {span} cells, over the {MAX_CELLS:,} a lattice may: are the spacing and the "
            "mesh in metres (--scale 0.001 reads a mesh in mm)?"
        )
    return origin, cells


def support_planes(selectors: list[dict[str, Any]]) -> Planes:
    """Per axis, the coordinates of the faces of the ``box`` selectors among ``selectors`` (a
    spec's ``fixed``): where a held box cuts the solid, the lattice puts a plane of nodes on
    its face (:func:`lattice`), so the lattice holds the solid where the spec does (off by half
    a cell it would hold a layer the reference leaves free: docs/explanation/organs-lattice.md)."""
    planes: list[list[float]] = [[], [], []]
    for selector in selectors:
        box = selector.get("box")
        if box is not None:
            for corner in box:
                for a in range(3):
                    planes[a].append(float(corner[a]))
    return planes if any(planes) else None


def _index_ranges(
    lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, cells: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """(E, D) first and last cell index whose centre lies in each element's box [lo, hi]
    (and perhaps one more on either side)."""
    d = lo.shape[1]
    # Widened by a hair: a centre on the box's edge must stay a candidate despite rounding
    # (the inside tests decide).
    first = np.ceil((lo - origin[:d]) / spacing - 0.5 - 1e-6).astype(np.int64)
    last = np.floor((hi - origin[:d]) / spacing - 0.5 + 1e-6).astype(np.int64)
    return np.maximum(first, 0), np.minimum(last, cells[:d] - 1)


def _pairs(first: np.ndarray, last: np.ndarray) -> Any:
    """Yields (element, (K, D) cell indices) chunks: every cell index in each element's range."""
    extent = np.maximum(last - first + 1, 0)
    counts = np.prod(extent, axis=1)
    ends = np.cumsum(counts)
    start = 0
    while start < len(counts):
        base = ends[start - 1] if start else 0
        stop = int(np.searchsorted(ends, base + CHUNK, side="right"))
        stop = max(stop, start + 1)
        c = counts[start:stop]
        element = np.repeat(np.arange(start, stop), c)
        local = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        ext = extent[element]
        index = np.empty((len(element), first.shape[1]), dtype=np.int64)
        for a in range(first.shape[1]):
            index[:, a] = first[element, a] + local % ext[:, a]
            local = local // ext[:, a]
        yield element, index
        start = stop


def voxelise_tetrahedra(
    points: np.ndarray,
    tets: np.ndarray,
    spacing: float,
    planes: Planes = None,
    grid: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(cx, cy, cz) bool occupancy and the lattice origin: cells whose centre lies in a
    tetrahedron (barycentric coordinates all >= -:data:`TOLERANCE`); ``planes`` as
    :func:`lattice`'s. ``grid`` (origin (3,), m; cells per axis (3,)) gives the lattice instead
    (a graded lattice's finer level on its coarse level's grid)."""
    tets = np.asarray(tets, dtype=np.int64)
    if tets.min() < 0 or tets.max() >= len(points):
        raise MeshError("a cell names a node that is not in the mesh")
    used = points[np.unique(tets)]
    if grid is None:
        origin, cells = lattice(used.min(axis=0), used.max(axis=0), spacing, planes)
    else:
        origin, cells = np.asarray(grid[0], dtype=float), np.asarray(grid[1], dtype=np.int64)
    v = points[tets]  # (T, 4, 3)
    edges = edge_matrices(v)  # (T, 3, 3): columns b-a, c-a, d-a
    det = np.linalg.det(edges)
    size = np.abs(edges).max(axis=(1, 2))
    keep = np.abs(det) > 1e-12 * size**3  # flat tetrahedra hold no cell centre
    v, edges = v[keep], edges[keep]
    inverse = np.linalg.inv(edges)
    occupancy = np.zeros(cells, dtype=bool)
    if not len(v):
        return occupancy, origin
    first, last = _index_ranges(v.min(axis=1), v.max(axis=1), origin, cells, spacing)
    for element, index in _pairs(first, last):
        centre = origin + spacing * (index + 0.5)
        lam = np.einsum("kij,kj->ki", inverse[element], centre - v[element, 0])
        inside = (lam.min(axis=1) >= -TOLERANCE) & (lam.sum(axis=1) <= 1 + TOLERANCE)
        hit = index[inside]
        occupancy[hit[:, 0], hit[:, 1], hit[:, 2]] = True
    return occupancy, origin


SAMPLES_MAX = 8
""":func:`centroid_cells` samples a tetrahedron with at most this many points along an edge."""


def centroid_cells(
    points: np.ndarray, tets: np.ndarray, spacing: float, origin: np.ndarray, cells: np.ndarray
) -> np.ndarray:
    """(cx, cy, cz) bool: the cells of the lattice at ``origin`` (3,), ``spacing`` (m),
    ``cells`` (3,) per axis, that hold a point inside a tetrahedron of ``tets`` (T, 4) on
    ``points`` (N, 3): its centroid, and for one longer than a cell, points of a barycentric
    grid at most a cell apart (n per edge, ``(m + 1/4) / (n + 1)`` for the 4-tuples m of sum n,
    all strictly inside it). A wall thinner than the cells' centres are apart can pass between
    every centre (a flat cap parallel to a plane of the lattice holds none); its tetrahedra's
    own points still fall in every cell it crosses."""
    cells = np.asarray(cells, dtype=np.int64)
    occupancy = np.zeros(cells, dtype=bool)
    tets = np.asarray(tets, dtype=np.int64)
    if not len(tets):
        return occupancy
    v = points[tets]  # (T, 4, 3)
    longest = np.linalg.norm(v[:, :, None] - v[:, None], axis=3).max(axis=(1, 2))
    per_edge = np.clip(np.ceil(longest / spacing) - 1, 0, SAMPLES_MAX).astype(np.int64)
    for n in np.unique(per_edge):
        m = np.array([c for c in np.ndindex(*(n + 1,) * 3) if sum(c) <= n], dtype=float).reshape(
            -1, 3
        )
        m = np.column_stack([m, n - m.sum(axis=1)])
        weights = (m + 0.25) / (n + 1)  # (P, 4), each row sums to 1
        inside = np.einsum("pc,tcx->tpx", weights, v[per_edge == n]).reshape(-1, 3)
        index = np.floor((inside - origin) / spacing).astype(np.int64)
        index = index[((index >= 0) & (index < cells)).all(axis=1)]
        occupancy[index[:, 0], index[:, 1], index[:, 2]] = True
    return occupancy


def open_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) edges (sorted node pairs) that belong to an odd number of ``triangles``: empty
    for a surface that encloses a volume."""
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts % 2 == 1]


def voxelise_surface(
    points: np.ndarray, triangles: np.ndarray, spacing: float, planes: Planes = None
) -> tuple[np.ndarray, np.ndarray]:
    """(cx, cy, cz) bool occupancy and the lattice origin: cells whose centre a closed triangle
    surface encloses (odd number of crossings of a vertical ray below the centre).

    Raises:
        MeshError: the surface is open (an edge belongs to an odd number of triangles).
    """
    triangles = np.asarray(triangles, dtype=np.int64)
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise MeshError("a cell names a node that is not in the mesh")
    # The same point given twice (STL repeats them per triangle) is one vertex.
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    triangles = inverse.reshape(-1)[triangles]
    triangles = triangles[
        (triangles[:, 0] != triangles[:, 1])
        & (triangles[:, 1] != triangles[:, 2])
        & (triangles[:, 0] != triangles[:, 2])
    ]
    if not len(triangles):
        raise MeshError("the surface has no triangle with three distinct corners")
    loose = open_edges(triangles)
    if len(loose):
        a, b = unique[loose[0, 0]], unique[loose[0, 1]]
        raise MeshError(
            f"the surface is not closed: {len(loose)} of its edges belong to an odd number of "
            f"triangles (one runs from {_fmt(a)} to {_fmt(b)}), so it encloses no volume to "
            "voxelise: close its holes, or give a tetrahedral mesh of the solid"
        )
    used = unique[np.unique(triangles)]
    origin, cells = lattice(used.min(axis=0), used.max(axis=0), spacing, planes)
    v = unique[triangles]  # (T, 3, 3)
    # Each edge evaluated from its lower-numbered vertex: bitwise the same for both triangles.
    ends = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2)  # (T, 3, 2): a -> b
    flip = ends[:, :, 0] > ends[:, :, 1]
    low = np.where(flip, ends[:, :, 1], ends[:, :, 0])
    high = np.where(flip, ends[:, :, 0], ends[:, :, 1])
    ex = unique[high, 0] - unique[low, 0]
    ey = unique[high, 1] - unique[low, 1]
    area2 = (v[:, 1, 0] - v[:, 0, 0]) * (v[:, 2, 1] - v[:, 0, 1]) - (v[:, 1, 1] - v[:, 0, 1]) * (
        v[:, 2, 0] - v[:, 0, 0]
    )
    keep = area2 != 0  # a triangle seen edge-on from below is crossed by no (perturbed) ray
    toggles = np.zeros((cells[0], cells[1], cells[2] + 1), dtype=np.int64)
    tri = np.flatnonzero(keep)
    first, last = _index_ranges(
        v[tri, :, :2].min(axis=1), v[tri, :, :2].max(axis=1), origin, cells, spacing
    )
    for element, index in _pairs(first, last):
        t = tri[element]
        px = (origin[0] + spacing * (index[:, 0] + 0.5))[:, None]
        py = (origin[1] + spacing * (index[:, 1] + 0.5))[:, None]
        lx, ly = unique[low[t], 0], unique[low[t], 1]
        hx, hy = unique[high[t], 0], unique[high[t], 1]
        w = ex[t] * (py - ly) - ey[t] * (px - lx)  # (K, 3) canonical edge functions
        sign = _orientation(
            lx, ly, hx, hy, np.broadcast_to(px, w.shape), np.broadcast_to(py, w.shape), w
        )
        tie = np.where(ey[t] != 0, -np.sign(ey[t]), np.sign(ex[t]))  # sign of w at (e, e^2)
        sign = np.where(sign != 0, sign, tie)
        sign = np.where(flip[t], -sign, sign)  # the triangle's own edge direction
        inside = (sign == sign[:, :1]).all(axis=1)
        if not inside.any():
            continue
        t, index, w = t[inside], index[inside], np.where(flip[t[inside]], -1, 1) * w[inside]
        # Barycentric weight of each corner: the edge function of the opposite edge.
        weight = w[:, [1, 2, 0]] / area2[t][:, None]
        z = (weight * v[t, :, 2]).sum(axis=1)
        above = np.ceil((z - origin[2]) / spacing - 0.5).astype(np.int64)
        np.add.at(toggles, (index[:, 0], index[:, 1], np.clip(above, 0, cells[2])), 1)
    occupancy = np.cumsum(toggles, axis=2)[:, :, : cells[2]] % 2 == 1
    return occupancy, origin


ORIENT_BOUND = (3.0 + 16.0 * 2.0**-53) * 2.0**-53
"""Shewchuk's error bound for the floating-point 2-D orientation (``ccwerrboundA``): a value
smaller than this times the sum of the products' magnitudes may have the wrong sign."""


def _orientation(
    lx: np.ndarray,
    ly: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    w: np.ndarray,
) -> np.ndarray:
    """The exact sign of ``(hx - lx)(py - ly) - (hy - ly)(px - lx)``, whose rounded value is
    ``w``: the rounded sign where the error bound certifies it, else exact rational arithmetic
    (a ray passing within rounding of an edge's line: rare, except on meshes aligned with the
    lattice)."""
    sign = np.sign(w)
    bound = ORIENT_BOUND * (np.abs((hx - lx) * (py - ly)) + np.abs((hy - ly) * (px - lx)))
    for k in zip(*np.nonzero(np.abs(w) <= bound), strict=True):
        f = [Fraction(float(a[k])) for a in (lx, ly, hx, hy, px, py)]
        exact = (f[2] - f[0]) * (f[5] - f[1]) - (f[3] - f[1]) * (f[4] - f[0])
        sign[k] = (exact > 0) - (exact < 0)
    return sign


def one_piece(occupancy: np.ndarray) -> tuple[np.ndarray, int]:
    """The largest piece of ``occupancy`` (cx, cy, cz) whose cells are joined through shared
    faces, and how many cells the other pieces had. A cell joined only along an edge or at a
    corner is its own piece (two hexahedra sharing an edge hinge on it: the FEM finds part of
    the solid not held)."""
    from scipy.ndimage import label

    labels, pieces = label(occupancy)  # the default structure: the 6 face neighbours
    if pieces <= 1:
        return occupancy, 0
    sizes = np.bincount(labels.ravel())[1:]
    keep = labels == 1 + int(np.argmax(sizes))
    return keep, int(occupancy.sum() - keep.sum())


def _crop(occupancy: np.ndarray, origin: np.ndarray, spacing: float) -> tuple[np.ndarray, Any]:
    """The occupancy cropped to its solid cells, and the origin moved with it."""
    if not occupancy.any():
        raise MeshError(
            f"no cell centre lies inside the solid at h = {spacing:.4g} m: the spacing is too "
            "coarse for it (or the mesh is in other units: see --scale)"
        )
    lo = [int(np.flatnonzero(occupancy.any(axis=tuple(b for b in range(3) if b != a)))[0])
          for a in range(3)]  # fmt: skip
    hi = [int(np.flatnonzero(occupancy.any(axis=tuple(b for b in range(3) if b != a)))[-1])
          for a in range(3)]  # fmt: skip
    cropped = occupancy[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]
    return cropped, origin + spacing * np.asarray(lo)


def _fmt(v: Any) -> str:
    return "[" + ", ".join(f"{float(x):.4g}" for x in v) + "]"
