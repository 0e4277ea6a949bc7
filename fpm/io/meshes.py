"""Mesh files in, problem specs out: real geometry for the calibration.

A mesh is read with meshio (Gmsh ``.msh``, VTK ``.vtu``/``.vtk``, Abaqus ``.inp``, STL, ...) and
becomes a spec geometry (:mod:`fpm.model.spec`):

- **hexahedra** (8-node; the corners of 20- and 27-node ones) become a ``mesh`` geometry as they
  are: meshio hands them over in VTK node order, which is :mod:`fpm.model.hexahedron`'s; a
  hexahedron numbered inside out (negative volume) is renumbered, and nodes in no hexahedron are
  dropped;
- **tetrahedra** (and wedges and pyramids, split into tetrahedra) and **closed triangle
  surfaces** (quads split in two) are voxelised into a ``voxels`` lattice at a spacing ``h`` the
  user chooses: a cell is solid when its centre lies inside the solid. Both inside tests are
  exact and vectorised over cells (no per-cell Python loop):

  * tetrahedra: barycentric coordinates of the cell centres in each tetrahedron, the candidates
    found by binning every tetrahedron's bounding box onto the lattice;
  * surfaces: parity of the crossings of a vertical ray from each cell centre, the triangles
    binned onto the lattice's columns by their bounding boxes; a ray through an edge or a
    vertex is decided by simulation of simplicity (the ray origin perturbed by (e, e^2)), with
    every edge evaluated once from its lower-numbered vertex, so a crossing on an edge shared
    by two triangles counts exactly once. A surface that does not enclose a volume (an edge
    that belongs to an odd number of triangles) is refused with a clear message.

The lattice is centred on the mesh's bounding box, ``ceil(extent / h)`` cells per axis, and
cropped to the solid cells. :func:`spec_from_mesh` adds the material, fixed nodes and load
cases given as short selector strings (:func:`parse_selector`, :func:`parse_force`) and
``fpmcal spec from-mesh`` is its command line.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from ..model.spec import FACES
from .errors import MeshError

TOLERANCE = 1e-9
"""A cell centre within this (relative) barycentric margin of a tetrahedron counts as inside it:
a centre on a face shared by two tetrahedra is never lost to rounding."""
CHUNK = 1 << 21
"""Candidate (element, cell) pairs handled at once (bounds the temporaries)."""

VOLUME_CELLS = {"tetra": 4, "tetra10": 4, "wedge": 6, "wedge15": 6, "pyramid": 5, "pyramid13": 5}
"""meshio cell types voxelised as volumes, with their corner count (corners come first)."""
HEXAHEDRA = {"hexahedron": 8, "hexahedron20": 8, "hexahedron24": 8, "hexahedron27": 8}
SURFACE_CELLS = {"triangle": 3, "triangle6": 3, "triangle7": 3, "quad": 4, "quad8": 4, "quad9": 4}

# Tetrahedra of the volume cells, by local corner index (VTK order).
_SPLIT = {
    4: np.array([[0, 1, 2, 3]]),
    5: np.array([[0, 1, 2, 4], [0, 2, 3, 4]]),
    6: np.array([[0, 1, 2, 3], [1, 2, 3, 4], [2, 3, 4, 5]]),
    8: np.array(
        [[0, 1, 3, 4], [1, 2, 3, 6], [1, 4, 5, 6], [3, 4, 6, 7], [1, 3, 4, 6]]
    ),  # 5 tetrahedra of a hexahedron
}
_MIRROR = np.array([0, 3, 2, 1, 4, 7, 6, 5])
"""Renumbering that turns an inside-out hexahedron right side out."""


@dataclass
class MeshGeometry:
    """A spec geometry made from a mesh.

    Attributes:
        geometry: the spec's ``geometry`` (a ``mesh`` or ``voxels`` dict).
        kind: what the mesh held: ``"hexahedra"``, ``"tetrahedra"`` or ``"surface"``.
        notes: what the user should know (cells dropped, renumbered, the lattice's size).
    """

    geometry: dict[str, Any]
    kind: str
    notes: list[str] = field(default_factory=list)
    tetrahedra: dict[str, Any] | None = None
    """For tetrahedra: the mesh as the spec's ``reference.mesh`` carries it,
    ``{"nodes": [[x, y, z], ...], "tetrahedra": [[i, j, k, l], ...]}`` (m, after ``scale``;
    0-based; only the nodes the tetrahedra use; every tetrahedron of positive volume), with
    ``"tags"`` (one integer per tetrahedron) when the mesh has integer cell data
    (:func:`cell_tags`)."""


def mesh_suffix(path: str | Path) -> str | None:
    """The mesh format suffix of ``path`` meshio knows (``.vtu``, ``.vol.gz``, ...), or None."""
    import meshio

    name = Path(path).name.lower()
    known = sorted(meshio.extension_to_filetypes, key=len, reverse=True)
    return next((s for s in known if name.endswith(s)), None)


def legacy_format(path: Path) -> str | None:
    """``"gmsh1"`` for a Gmsh legacy v1 ``.msh`` ($NOD/$ELM), ``"polydata"`` for a legacy VTK
    POLYDATA ``.vtk`` (meshio reads neither), else None; from the file's first lines."""
    suffix = path.suffix.lower()
    if suffix not in (".msh", ".vtk"):
        return None
    try:
        with open(path, "rb") as f:
            head = f.read(4096).decode("latin-1")
    except OSError:
        return None
    if suffix == ".msh" and head.lstrip().startswith("$NOD"):
        return "gmsh1"
    if suffix == ".vtk" and "DATASET POLYDATA" in head.upper():
        return "polydata"
    return None


def read_mesh(path: str | Path) -> Any:
    """The meshio Mesh in ``path``; :class:`MeshError` with the reason when it cannot be read.

    (meshio prints and exits on a file it cannot parse; that is caught here.)
    """
    import meshio

    p = Path(path)
    if not p.is_file():
        raise MeshError(f"{p}: no such mesh file")
    if mesh_suffix(p) is None:
        raise MeshError(
            f"{p}: not a mesh format meshio reads by its suffix (known: .msh, .vtu, .vtk, "
            ".inp, .stl, .obj, .ply, .off, .mesh, .xdmf, ...)"
        )
    legacy = legacy_format(p)
    printed = io.StringIO()
    try:
        if legacy is not None:
            from .legacy import read_legacy

            return read_legacy(p, legacy)
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            return meshio.read(p)
    except MeshError:
        raise
    except (Exception, SystemExit) as e:
        said = " ".join((printed.getvalue() + " " + str(e)).split()).strip(" 1")
        raise MeshError(f"{p}: cannot read it as a mesh ({said or type(e).__name__})") from None


def geometry_from_mesh(
    mesh: Any,
    *,
    spacing: float | None = None,
    connectivity: str = "full",
    scale: float = 1.0,
    voxelise: bool = False,
) -> MeshGeometry:
    """The spec geometry of a meshio ``mesh`` (see the module docstring).

    Args:
        mesh: a ``meshio.Mesh``.
        spacing: lattice spacing h, m (after ``scale``); needed unless the mesh is hexahedral.
        connectivity: the springs (``axis``, ``axis+face``, ``full``).
        scale: multiplies the coordinates (e.g. 0.001 for a mesh in mm).
        voxelise: voxelise a hexahedral mesh too (resample it onto a lattice of ``spacing``).
    """
    points = np.asarray(mesh.points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"the mesh has {points.shape[-1]}-D points: a solid needs 3-D coordinates")
    if not np.all(np.isfinite(points)):
        raise MeshError("the mesh has non-finite coordinates")
    points = points * float(scale)
    blocks = [(c.type, np.asarray(c.data, dtype=np.int64)) for c in mesh.cells]
    tag_name, found_tags = cell_tags(mesh)
    block_tags: list[np.ndarray | None] = list(found_tags) or [None] * len(blocks)
    hexes = [d[:, :8] for t, d in blocks if t in HEXAHEDRA and len(d)]
    hex_tags = [
        g for (t, d), g in zip(blocks, block_tags, strict=True) if t in HEXAHEDRA and len(d)
    ]
    volumes = [(VOLUME_CELLS[t], d[:, : VOLUME_CELLS[t]]) for t, d in blocks if t in VOLUME_CELLS]
    volume_tags = [g for (t, _), g in zip(blocks, block_tags, strict=True) if t in VOLUME_CELLS]
    surfaces = [
        (SURFACE_CELLS[t], d[:, : SURFACE_CELLS[t]]) for t, d in blocks if t in SURFACE_CELLS
    ]
    types = ", ".join(sorted({f"{len(d)} {t}" for t, d in blocks})) or "no cells"
    if hexes and not voxelise and not any(len(d) for _, d in volumes):
        return _hexahedral(points, np.concatenate(hexes), connectivity, spacing)
    if hexes and not voxelise:
        raise MeshError(
            f"the mesh mixes hexahedra with other volume cells ({types}): voxelise it "
            "(--voxelise, with --spacing) or convert it to hexahedra only"
        )
    if spacing is None or not spacing > 0:
        raise MeshError(
            f"this mesh ({types}) is voxelised into a lattice: give its spacing h > 0 in m "
            "(--spacing), e.g. a tenth of the solid's smallest extent"
        )
    volumes += [(8, h) for h in hexes]
    volume_tags += hex_tags
    tet_tags = None
    if any(len(d) for _, d in volumes):
        tets = np.concatenate([d[:, _SPLIT[n]].reshape(-1, 4) for n, d in volumes if len(d)])
        if tag_name is not None:  # each tetrahedron keeps the tag of the cell it came from
            tet_tags = np.concatenate(
                [
                    np.repeat(np.zeros(len(d), np.int64) if g is None else g, len(_SPLIT[n]))
                    for (n, d), g in zip(volumes, volume_tags, strict=True)
                    if len(d)
                ]
            )
        occupancy, origin = voxelise_tetrahedra(points, tets, spacing)
        kind, what = "tetrahedra", f"{len(tets)} tetrahedra"
    elif any(len(d) for _, d in surfaces):
        tris = np.concatenate(
            [d[:, [[0, 1, 2], [0, 2, 3]][: n - 2]].reshape(-1, 3) for n, d in surfaces if len(d)]
        )
        occupancy, origin = voxelise_surface(points, tris, spacing)
        kind, what = "surface", f"a closed surface of {len(tris)} triangles"
    else:
        raise MeshError(
            f"the mesh has no volume cells and no surface triangles ({types}): give "
            "hexahedra, tetrahedra or a closed triangle surface"
        )
    occupancy, dropped = one_piece(occupancy)
    occupancy, origin = _crop(occupancy, origin, spacing)
    cells = int(occupancy.sum())
    notes = [
        f"voxelised {what} at h = {spacing:.4g} m: {cells} cells of a "
        f"{'x'.join(map(str, occupancy.shape))} lattice"
    ]
    if dropped:
        volume = dropped * spacing**3
        notes.append(
            f"dropped {dropped} cells ({volume:.3g} m^3, {100 * dropped / (dropped + cells):.2g}% "
            "of the volume) joined to the rest by less than a face (an edge, a corner, or "
            "nothing): the FEM could not hold them"
        )
    geometry = {
        "type": "voxels",
        "occupancy": occupancy.astype(np.uint8).tolist(),
        "spacing": [spacing] * 3,
        "origin": origin.tolist(),
        "connectivity": connectivity,
    }
    reference = None
    if kind == "tetrahedra":
        kept = origin + spacing * (np.argwhere(occupancy) + 0.5)  # the lattice's cell centres
        reference = _reference_mesh(points, tets, tet_tags, kept, notes)
    if reference is not None and "tags" in reference:
        found = sorted(set(reference["tags"]))
        shown = ", ".join(map(str, found[:12])) + (", ..." if len(found) > 12 else "")
        notes.append(
            f"reference.mesh.tags: the cell data '{tag_name}' of each tetrahedron ({shown}): "
            'material.regions may select by it, {"selector": {"tag": t}}'
        )
    return MeshGeometry(geometry, kind, notes, reference)


TAG_NAMES = ("gmsh:physical", "medit:ref", "CellEntityIds", "region", "regions", "tag", "tags")
"""Cell data read as tags, in this order of preference (then any integer cell data)."""


def cell_tags(mesh: Any) -> tuple[str | None, list[np.ndarray]]:
    """The mesh's integer cell data to keep as tags (``reference.mesh.tags``, which
    ``material.regions`` selectors name): its name and one (n,) array per cell block; (None,
    []) when the mesh has none. Preferred names: :data:`TAG_NAMES`; else the first cell data
    whose values are all integers."""
    data = getattr(mesh, "cell_data", None) or {}
    names = [n for n in TAG_NAMES if n in data] + sorted(n for n in data if n not in TAG_NAMES)
    for name in names:
        arrays = data[name]
        if len(arrays) != len(mesh.cells):
            continue
        try:
            values = [
                np.asarray(a, dtype=float).reshape(len(c.data), -1)
                for a, c in zip(arrays, mesh.cells, strict=True)
            ]
        except (TypeError, ValueError):
            continue
        if all(
            v.shape[1] == 1 and np.all(np.isfinite(v)) and np.all(v == np.round(v)) for v in values
        ):
            return name, [v[:, 0].astype(np.int64) for v in values]
    return None, []


def _reference_mesh(
    points: np.ndarray,
    tets: np.ndarray,
    tags: np.ndarray | None,
    centres: np.ndarray,
    notes: list[str],
) -> dict[str, Any]:
    """``reference.mesh`` of the tetrahedra: used nodes only, inside-out tetrahedra renumbered,
    flat ones (no volume: e.g. from a split wedge) dropped; ``tags`` (one per tetrahedron)
    kept as its ``tags``. Of the mesh's pieces (:func:`face_pieces`) only those holding one
    of the lattice's cell ``centres`` (C, 3), m, are kept: the reference is the solid the
    lattice is (:func:`one_piece` drops the cells of the others), and a piece joined by less
    than a face would not be held, and a load spread onto it (:mod:`fpm.fem.loads`) could not
    be carried. A note in ``notes`` says what was left out."""
    from ..fem.tet10 import locate
    from ..model.tetrahedra import DEGENERATE, EDGES, tetrahedron_volumes

    used, inverse = np.unique(tets, return_inverse=True)
    tets, nodes = inverse.reshape(-1, 4), points[used]
    volume = tetrahedron_volumes(nodes, tets)
    v = nodes[tets]
    longest = np.linalg.norm(v[:, EDGES[:, 1]] - v[:, EDGES[:, 0]], axis=2).max(axis=1)
    solid = np.abs(volume) > DEGENERATE * longest**3
    tets = tets[solid]
    volume = tetrahedron_volumes(nodes, tets)
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    pieces = face_pieces(nodes, tets)
    if pieces.max() > 0:
        held = np.zeros(pieces.max() + 1, dtype=bool)
        held[pieces[locate(nodes, tets, centres).element]] = True
        keep = held[pieces]
        if not keep.all():
            notes.append(
                f"reference.mesh: left out {int((~keep).sum())} tetrahedra "
                f"({float(np.abs(volume[~keep]).sum()):.3g} m^3) in {int((~held).sum())} "
                "piece(s) joined to the rest by less than a face and holding no lattice cell: "
                "the reference is the solid the lattice is"
            )
            tets = tets[keep]
            solid[np.flatnonzero(solid)[~keep]] = False
    used, inverse = np.unique(tets, return_inverse=True)
    out: dict[str, Any] = {
        "nodes": nodes[used].tolist(),
        "tetrahedra": inverse.reshape(-1, 4).tolist(),
    }
    if tags is not None:
        out["tags"] = [int(t) for t in tags[solid]]
    return out


def _hexahedral(
    points: np.ndarray, hexes: np.ndarray, connectivity: str, spacing: float | None
) -> MeshGeometry:
    from ..model.geometry import hexahedron_volumes

    notes = []
    if spacing is not None:
        notes.append(
            "the mesh is hexahedral and is used as it is (--spacing ignored; --voxelise "
            "resamples it onto a lattice)"
        )
    if hexes.min() < 0 or hexes.max() >= len(points):
        raise MeshError("a hexahedron names a node that is not in the mesh")
    used, inverse = np.unique(hexes, return_inverse=True)
    hexes = inverse.reshape(-1, 8)
    nodes = points[used]
    if len(used) < len(points):
        notes.append(f"{len(points) - len(used)} nodes in no hexahedron were dropped")
    volume = hexahedron_volumes(nodes, hexes)
    inside_out = volume < 0
    if inside_out.any():
        hexes[inside_out] = hexes[inside_out][:, _MIRROR]
        notes.append(
            f"{int(inside_out.sum())} hexahedra numbered inside out (negative volume) were "
            "renumbered"
        )
    geometry = {
        "type": "mesh",
        "nodes": nodes.tolist(),
        "hexahedra": hexes.tolist(),
        "connectivity": connectivity,
    }
    return MeshGeometry(geometry, "hexahedra", notes)


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin, cells per axis) of the lattice of ``spacing`` centred on the box [lo, hi]:
    ``ceil(extent / h)`` cells per axis (at least 1)."""
    extent = np.asarray(hi, dtype=float) - np.asarray(lo, dtype=float)
    cells = np.maximum(1, np.ceil(extent / spacing - 1e-9)).astype(np.int64)
    origin = (np.asarray(lo) + np.asarray(hi)) / 2 - cells * spacing / 2
    return origin, cells


def cell_centres(origin: np.ndarray, cells: np.ndarray, spacing: float) -> list[np.ndarray]:
    """Per axis, the coordinates of the lattice's cell centres."""
    return [origin[a] + spacing * (np.arange(cells[a]) + 0.5) for a in range(3)]


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
    points: np.ndarray, tets: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """(cx, cy, cz) bool occupancy and the lattice origin: cells whose centre lies in a
    tetrahedron (barycentric coordinates all >= -:data:`TOLERANCE`)."""
    tets = np.asarray(tets, dtype=np.int64)
    if tets.min() < 0 or tets.max() >= len(points):
        raise MeshError("a cell names a node that is not in the mesh")
    used = points[np.unique(tets)]
    origin, cells = lattice(used.min(axis=0), used.max(axis=0), spacing)
    v = points[tets]  # (T, 4, 3)
    edges = np.transpose(v[:, 1:] - v[:, :1], (0, 2, 1))  # (T, 3, 3): columns b-a, c-a, d-a
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


def open_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) edges (sorted node pairs) that belong to an odd number of ``triangles``: empty
    for a surface that encloses a volume."""
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts % 2 == 1]


def voxelise_surface(
    points: np.ndarray, triangles: np.ndarray, spacing: float
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
    origin, cells = lattice(used.min(axis=0), used.max(axis=0), spacing)
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


def face_pieces(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) the piece of each tetrahedron ``tets`` (T, 4) on ``nodes`` (N, 3): tetrahedra that
    share a face (three corners at the same positions, whether or not the mesh numbers them
    as the same nodes) are in one piece; pieces numbered from 0."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, same = np.unique(nodes, axis=0, return_inverse=True)
    corners = same.reshape(-1)[tets]
    faces = np.sort(corners[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, face = np.unique(faces, axis=0, return_inverse=True)
    count = len(tets) + int(face.max()) + 1
    owner = np.repeat(np.arange(len(tets)), 4)
    graph = coo_matrix(
        (np.ones(len(owner)), (owner, len(tets) + face.reshape(-1))), shape=(count, count)
    )
    return connected_components(graph, directed=False)[1][: len(tets)]


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


# ---------------------------------------------------------------- selectors as short strings

SELECTOR_HELP = "face:z- | node:I | at:X,Y,Z | nearest:X,Y,Z | box:X0,Y0,Z0:X1,Y1,Z1 (lengths in m)"
FORCE_HELP = (
    "SELECTOR:FX,FY,FZ[:distribute] (N; e.g. nearest:0,0,0.05:0,0,-0.5 or "
    "face:z+:0,0,-2:distribute); several forces of one load case separated by ';'"
)


def _vector(text: str, what: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what} must be three numbers x,y,z (got {text!r})")
    return values


def _selector(parts: list[str], text: str) -> tuple[dict[str, Any], list[str]]:
    """The selector at the start of ``parts`` and the parts left over."""
    kind = parts[0].strip().lower()
    if kind == "face":
        if len(parts) < 2 or parts[1].strip() not in FACES:
            raise ValueError(f"{text!r}: a face is one of x-, x+, y-, y+, z-, z+ (e.g. face:z-)")
        return {"face": parts[1].strip()}, parts[2:]
    if kind == "node":
        try:
            node = int(parts[1])
        except (IndexError, ValueError):
            raise ValueError(f"{text!r}: give a node index, e.g. node:12") from None
        return {"node": node}, parts[2:]
    if kind in ("at", "nearest"):
        if len(parts) < 2:
            raise ValueError(f"{text!r}: give a point, e.g. {kind}:0.05,0.05,0.1")
        return {kind: _vector(parts[1], f"{text!r}: the point")}, parts[2:]
    if kind == "box":
        if len(parts) < 3:
            raise ValueError(f"{text!r}: give two corners, e.g. box:0,0,0:0.1,0.1,0.01")
        lo = _vector(parts[1], f"{text!r}: the low corner")
        hi = _vector(parts[2], f"{text!r}: the high corner")
        return {"box": [lo, hi]}, parts[3:]
    raise ValueError(f"{text!r}: a selector is {SELECTOR_HELP}")


def parse_selector(text: str) -> dict[str, Any]:
    """A spec selector from its short form: ``face:z-``, ``node:12``, ``at:x,y,z``,
    ``nearest:x,y,z`` or ``box:x0,y0,z0:x1,y1,z1``."""
    selector, rest = _selector(text.split(":"), text)
    if rest:
        raise ValueError(f"{text!r}: unexpected {':'.join(rest)!r} after the selector")
    return selector


def parse_force(text: str) -> list[dict[str, Any]]:
    """The forces of one load case from their short form, ``SELECTOR:FX,FY,FZ[:distribute]``,
    several separated by ``;``."""
    forces = []
    for one in text.split(";"):
        one = one.strip()
        if not one:
            continue
        selector, rest = _selector(one.split(":"), one)
        if not rest:
            raise ValueError(f"{one!r}: give the force after the selector, e.g. {one}:0,0,-1")
        force = {**selector, "vector": _vector(rest[0], f"{one!r}: the force")}
        flags = [r.strip().lower() for r in rest[1:]]
        if flags and flags != ["distribute"]:
            raise ValueError(f"{one!r}: after the force only ':distribute' may follow")
        if flags:
            force["distribute"] = True
        forces.append(force)
    if not forces:
        raise ValueError(f"{text!r}: no force given ({FORCE_HELP})")
    return forces


def spec_from_mesh(
    mesh: Any,
    *,
    fix: list[str],
    forces: list[str],
    youngs_modulus: float,
    poisson_ratio: float,
    density: float = 1000.0,
    spacing: float | None = None,
    connectivity: str = "full",
    scale: float = 1.0,
    voxelise: bool = False,
    name: str | None = None,
    dt: float | str = "auto",
    voxel_reference: bool = False,
    conform: bool = False,
) -> tuple[dict[str, Any], list[str]]:
    """A problem spec for a mesh file (or a ``meshio.Mesh``), and notes for the user.

    Args:
        mesh: a path meshio reads, or a ``meshio.Mesh``.
        fix: fixed nodes, each a short selector (:func:`parse_selector`), e.g. ``"face:z-"``.
        forces: one string per load case (:func:`parse_force`), e.g.
            ``"nearest:0,0,0.05:0,0,-0.5"``.
        youngs_modulus, poisson_ratio, density: the material (Pa, -, kg/m^3).
        spacing, connectivity, scale, voxelise: as :func:`geometry_from_mesh`.
        name: the spec's name (default: the file's name).
        dt: the FPM time step, s, or ``"auto"`` (resolved by the fit: half the lattice's
            stability estimate at the fitted stiffness, at most 1 ms).
        voxel_reference: for a tetrahedral mesh, solve the FEM reference on the voxel lattice's
            hexahedra (the staircase) instead of on the tetrahedra; by default the spec keeps
            the tetrahedra in ``reference.mesh`` and the reference is solved on them with
            10-node tetrahedra (:mod:`fpm.fem.tet10`).
        conform: for a tetrahedral mesh, the surface-conforming lattice instead of the voxels
            (:func:`conform_spec`): the voxels' surface nodes moved onto the mesh's surface, a
            hexahedral ``mesh`` geometry (the staircase costs the voxels 5-22% against the
            tetrahedra on the organ of ``bench/tet_organ.py`` at h = 5 mm, the conforming
            lattice 1-2%).

    Raises:
        MeshError: the mesh cannot become a solid. ValueError: a bad selector or force.
        pydantic.ValidationError: the spec does not fit its solid (e.g. a box with no node).
    """
    from ..model.problem import load_problem

    if isinstance(mesh, str | Path):
        name = name or Path(mesh).name
        mesh = read_mesh(mesh)
    made = geometry_from_mesh(
        mesh, spacing=spacing, connectivity=connectivity, scale=scale, voxelise=voxelise
    )
    if not fix:
        raise ValueError(f"give the fixed nodes (--fix {SELECTOR_HELP})")
    if not forces:
        raise ValueError(f"give at least one load case (--force {FORCE_HELP})")
    spec: dict[str, Any] = {
        "name": name or "mesh",
        "material": {
            "youngs_modulus": youngs_modulus,
            "poisson_ratio": poisson_ratio,
            "density": density,
        },
        "geometry": made.geometry,
        "fixed": [parse_selector(s) for s in fix],
        "load_cases": [{"name": text.strip(), "forces": parse_force(text)} for text in forces],
    }
    if made.tetrahedra is not None and not voxel_reference:
        spec["reference"] = {"mesh": made.tetrahedra}
    conformed: list[str] = []
    if conform:
        spec, conformed = conform_spec(spec)
    problem = load_problem(spec)  # selectors checked against the nodes
    notes = made.notes + conformed + [f"{problem.n_nodes} nodes, h = {problem.h:.4g} m"]
    notes += problem.notes
    if made.tetrahedra is not None:
        notes.append(
            "FEM reference: the voxel lattice's hexahedra (--voxel-reference)"
            if voxel_reference
            else f"FEM reference: the {len(made.tetrahedra['tetrahedra'])} tetrahedra "
            "themselves (10-node, reference.mesh), read at the lattice nodes"
        )
    if dt == "auto":
        spec["fpm"] = {"dt": "auto"}
        notes.append(
            "fpm.dt = 'auto': half the lattice's stability estimate at the fitted stiffness, at "
            "most 1 ms (the result's dt says which)"
        )
    else:
        spec["fpm"] = {"dt": float(dt)}
    return spec, notes


KEPT_JACOBIAN = 0.1
""":func:`conform_lattice` keeps every hexahedron's smallest Jacobian determinant at least this
fraction of its voxel's."""


def conform_lattice(
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    mesh_nodes: np.ndarray,
    tets: np.ndarray,
    *,
    boxes: list[tuple[np.ndarray, np.ndarray]] | None = None,
    tol: float = 0.0,
) -> np.ndarray:
    """(N, 3) a voxel lattice's ``nodes`` (N, 3), m, with its surface nodes (the corners of
    its boundary faces, ``hexahedra`` (H, 8)) moved onto their nearest points on the surface
    of the tetrahedra ``tets`` (T, 4) on ``mesh_nodes`` (M, 3): a surface-conforming lattice,
    the mesh's solid instead of its staircase. Each node goes all the way unless a hexahedron
    of it would keep less than :data:`KEPT_JACOBIAN` of its voxel's smallest Jacobian
    determinant; those hexahedra's surface nodes go 0.8 of the way, then 0.8 of that, until
    none does (every hexahedron stays positive).

    The selectors stay true: a node inside one of the ``boxes`` (lo, hi) (within ``tol``, m)
    moves only within it (its target clipped to the box); a node outside every box that
    would end up in one does not move.
    """
    from ..fem.elasticity import min_jacobian_determinants
    from ..fem.loads import lattice_surface
    from ..fem.tet10 import nearest_on_boundary

    x0 = np.asarray(nodes, dtype=float)
    surface = np.flatnonzero(lattice_surface(hexahedra, len(x0)))
    _, target, _ = nearest_on_boundary(
        np.asarray(mesh_nodes, dtype=float), np.asarray(tets), x0[surface]
    )
    share = np.ones(len(surface))
    boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes or []]

    def inside(x: np.ndarray) -> np.ndarray:
        """(B, S) each box's membership of the surface nodes at ``x`` (S, 3)."""
        return np.array(
            [np.all((x >= lo - tol) & (x <= hi + tol), axis=1) for lo, hi in boxes]
        ).reshape(len(boxes), len(x))

    held = inside(x0[surface])
    for (lo, hi), member in zip(boxes, held, strict=True):
        target[member] = np.clip(target[member], lo, hi)
    where = np.full(len(x0), -1)
    where[surface] = np.arange(len(surface))
    before = min_jacobian_determinants(x0[hexahedra])
    while True:
        x = x0.copy()
        x[surface] += share[:, None] * (target - x0[surface])
        strayed = np.any(inside(x[surface]) != held, axis=0)
        bad = min_jacobian_determinants(x[hexahedra]) < KEPT_JACOBIAN * before
        if not bad.any() and not strayed.any():
            return x
        share[strayed] = 0.0
        moved = where[np.unique(hexahedra[bad])]
        share[moved[moved >= 0]] *= 0.8


def conform_spec(spec: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """``spec`` (a ``voxels`` geometry with its tetrahedra in ``reference.mesh``, as
    :func:`spec_from_mesh` makes it) on the surface-conforming lattice
    (:func:`conform_lattice`): a hexahedral ``mesh`` geometry, the same nodes and hexahedra,
    the surface nodes on the mesh's surface; and notes.

    Every selector keeps the nodes it had on the voxels: a ``face`` (a plane of the voxels'
    bounding box, which a curved surface no longer has) becomes the box of the nodes within
    h/2 of that plane or beyond it (what the tetrahedral reference holds or loads for the face,
    :func:`fpm.fem.tet10.fixed_nodes`), an ``at`` the ``node`` it named; nodes in a box stay in
    it and nodes out of every box stay out. ``nearest`` and ``node`` selectors are kept as
    given.
    """
    from ..model.problem import load_problem

    mesh = (spec.get("reference") or {}).get("mesh")
    if spec["geometry"].get("type") != "voxels" or mesh is None:
        raise MeshError(
            "a conforming lattice moves a voxel lattice's surface onto its tetrahedral mesh's: "
            "give a tetrahedral mesh (not hexahedra, not a surface, not --voxel-reference)"
        )
    problem = load_problem(spec)
    x0 = problem.solid.nodes
    hexahedra = problem.solid.elements()
    assert hexahedra is not None
    h = float(min(spec["geometry"]["spacing"]))
    lo, hi = x0.min(axis=0), x0.max(axis=0)
    margin = np.max(hi - lo) + h
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    notes: list[str] = []
    rewritten: list[str] = []  # the selectors that had to change form

    def kept(selector: dict[str, Any]) -> dict[str, Any]:
        out = dict(selector)
        rewritten.extend(key for key in ("face", "at") if key in out)
        if "face" in out:
            axis, side = "xyz".index(out["face"][0]), out.pop("face")[1]
            box_lo, box_hi = lo - margin, hi + margin
            if side == "-":
                box_hi[axis] = lo[axis] + 0.499 * h
            else:
                box_lo[axis] = hi[axis] - 0.499 * h
            out["box"] = [box_lo.tolist(), box_hi.tolist()]
        if "at" in out:
            found = np.linalg.norm(x0 - np.asarray(out.pop("at")), axis=1)
            out["node"] = int(np.argmin(found))
        if "box" in out:
            boxes.append((np.asarray(out["box"][0]), np.asarray(out["box"][1])))
        return out

    conformed = dict(spec)
    conformed["fixed"] = [kept(s) for s in spec["fixed"]]
    for key in ("load_cases", "validation_cases"):
        if key in spec:
            conformed[key] = [
                {**case, "forces": [kept(f) for f in case["forces"]]} for case in spec[key]
            ]
    if rewritten:
        notes.append(
            "conforming lattice: face selectors became the boxes of the nodes within h/2 of "
            "the face (the surface no longer has flat faces), 'at' selectors the nodes they "
            "named"
        )
    x = conform_lattice(
        x0,
        hexahedra,
        np.asarray(mesh["nodes"], dtype=float),
        np.asarray(mesh["tetrahedra"]),
        boxes=boxes,
        tol=1e-3 * h,
    )
    surface = np.any(x != x0, axis=1)
    notes.append(
        f"conforming lattice: {int(surface.sum())} surface nodes moved onto the mesh's surface "
        f"(up to {np.linalg.norm(x - x0, axis=1).max() / h:.2g} h), every hexahedron keeping "
        f"at least {KEPT_JACOBIAN:g} of its voxel's smallest Jacobian"
    )
    conformed["geometry"] = {
        "type": "mesh",
        "nodes": x.tolist(),
        "hexahedra": hexahedra.tolist(),
        "connectivity": spec["geometry"].get("connectivity", "full"),
    }
    return conformed, notes


def read_reference(path: str | Path, load_cases: int) -> list[Any]:
    """A supplied reference field from a file, for ``reference.displacements``: (L, N, 3), m.

    - ``.json``: a list per load case of ``[ux, uy, uz]`` per lattice node, or an object with
      such a ``displacements`` list (what ``fpmcal fem`` writes);
    - ``.vtu`` (or any mesh file meshio reads): one point-data array of shape (N, 3) per load
      case, named ``displacement_J`` or ``fem_displacement_J`` (J = 1..L, as the ``vtu``
      export writes them), or a single ``displacement`` array when there is one load case;
      points in the lattice's node order.

    The shape and finiteness are checked when the spec is loaded (errors at
    ``reference.displacements``); here only what the file holds.

    Raises:
        ValueError: the file holds no such field (the message says what it looked for).
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        data = json.loads(path.read_text())
        if isinstance(data, dict):
            if "displacements" not in data:
                raise ValueError(f"{path}: a JSON reference needs a 'displacements' list")
            data = data["displacements"]
        if not isinstance(data, list):
            raise ValueError(f"{path}: a JSON reference is a list per load case")
        return data
    import meshio

    mesh = meshio.read(path)
    fields = []
    for j in range(1, load_cases + 1):
        names = [f"displacement_{j}", f"fem_displacement_{j}"]
        if load_cases == 1:
            names.append("displacement")
        found = next((n for n in names if n in mesh.point_data), None)
        if found is None:
            have = ", ".join(sorted(mesh.point_data)) or "none"
            raise ValueError(
                f"{path}: no point data {' or '.join(names)} for load case {j} (has: {have})"
            )
        fields.append(np.asarray(mesh.point_data[found], dtype=float).tolist())
    return fields
