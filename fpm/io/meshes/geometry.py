"""A meshio mesh as a spec geometry: hexahedra as they are, tetrahedra and surfaces voxelised
(:mod:`.voxelise`), the tetrahedra kept for the reference (``reference.mesh``), cell tags."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import MeshError
from .voxelise import (
    Planes,
    _crop,
    _fmt,
    centroid_cells,
    one_piece,
    voxelise_surface,
    voxelise_tetrahedra,
)

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


def geometry_from_mesh(
    mesh: Any,
    *,
    spacing: float | None = None,
    connectivity: str = "full",
    scale: float = 1.0,
    voxelise: bool = False,
    planes: Planes = None,
) -> MeshGeometry:
    """The spec geometry of a meshio ``mesh`` (see the module docstring).

    Args:
        mesh: a ``meshio.Mesh``.
        spacing: lattice spacing h, m (after ``scale``); needed unless the mesh is hexahedral.
        connectivity: the springs (``axis``, ``axis+face``, ``full``).
        scale: multiplies the coordinates (e.g. 0.001 for a mesh in mm).
        voxelise: voxelise a hexahedral mesh too (resample it onto a lattice of ``spacing``).
        planes: per axis, coordinates (after ``scale``) a plane of lattice nodes falls on
            where one cuts the solid (:func:`~fpm.io.meshes.voxelise.support_planes`).
    """
    points = mesh_points(mesh) * positive_scale(scale)
    blocks = [(c.type, np.asarray(c.data, dtype=np.int64)) for c in mesh.cells]
    tag_name, found_tags = cell_tags(mesh)
    block_tags: list[np.ndarray | None] = list(found_tags) or [None] * len(blocks)
    hexes = [d[:, :8] for t, d in blocks if t in HEXAHEDRA and len(d)]
    hex_tags = [
        g for (t, d), g in zip(blocks, block_tags, strict=True) if t in HEXAHEDRA and len(d)
    ]
    volumes = [(VOLUME_CELLS[t], d[:, : VOLUME_CELLS[t]]) for t, d in blocks if t in VOLUME_CELLS]
    volume_names = [t for t, _ in blocks if t in VOLUME_CELLS]
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
            "(--spacing), e.g. a tenth of the solid's smallest extent, or about how many "
            "lattice nodes it should have (--nodes), e.g. 2000 for a real-time model"
        )
    volumes += [(8, h) for h in hexes]
    volume_names += [t for t, d in blocks if t in HEXAHEDRA and len(d)]
    volume_tags += hex_tags
    tet_tags = None
    repairs: list[str] = []
    if any(len(d) for _, d in volumes):
        tets = np.concatenate([d[:, _SPLIT[n]].reshape(-1, 4) for n, d in volumes if len(d)])
        repairs = check_volume_cells(points, volumes, volume_names)
        if tag_name is not None:  # each tetrahedron keeps the tag of the cell it came from
            tet_tags = np.concatenate(
                [
                    np.repeat(np.zeros(len(d), np.int64) if g is None else g, len(_SPLIT[n]))
                    for (n, d), g in zip(volumes, volume_tags, strict=True)
                    if len(d)
                ]
            )
        occupancy, origin = voxelise_tetrahedra(points, tets, spacing, planes)
        kind, what = "tetrahedra", f"{len(tets)} tetrahedra"
    elif any(len(d) for _, d in surfaces):
        tris = np.concatenate(
            [d[:, [[0, 1, 2], [0, 2, 3]][: n - 2]].reshape(-1, 3) for n, d in surfaces if len(d)]
        )
        occupancy, origin = voxelise_surface(points, tris, spacing, planes)
        kind, what = "surface", f"a closed surface of {len(tris)} triangles"
    else:
        raise MeshError(
            f"the mesh has no volume cells and no surface triangles ({types}): give "
            "hexahedra, tetrahedra or a closed triangle surface"
        )
    kept, dropped = one_piece(occupancy)
    thickened = kind == "tetrahedra" and dropped > LOST_SHARE * occupancy.sum()
    if thickened:  # a wall thinner than h: its cell centres fall in and out of it
        occupancy = octant_occupancy(points, tets, spacing, origin, np.asarray(occupancy.shape))
        kept, dropped = one_piece(occupancy)
    occupancy, origin = _crop(kept, origin, spacing)
    cells = int(occupancy.sum())
    notes = [
        f"voxelised {what} at h = {spacing:.4g} m: {cells} cells of a "
        f"{'x'.join(map(str, occupancy.shape))} lattice"
    ] + repairs
    if thickened:
        notes.append(
            f"the solid is thinner than h = {spacing:.4g} m over much of it (its cell centres "
            "left it in pieces): a cell is solid where the mesh holds any of its eight octants' "
            "centres or its tetrahedra a point of theirs in it, so the thin parts are one cell "
            "thick, thicker than the mesh (a smaller "
            "spacing, or --nodes more, resolves them)"
        )
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


LOST_SHARE = 0.1
"""When the voxels' largest piece leaves out more than this share of their cells, the solid is
thinner than the spacing over much of it: :func:`geometry_from_mesh` voxelises it again with
:func:`octant_occupancy`."""


def octant_occupancy(
    points: np.ndarray, tets: np.ndarray, spacing: float, origin: np.ndarray, cells: np.ndarray
) -> np.ndarray:
    """(cx, cy, cz) bool: the cells of the lattice at ``origin`` (3,), ``spacing`` (m),
    ``cells`` (3,) per axis, where any of the 8 centres of their octants (the cells of h/2)
    lies in a tetrahedron of ``tets`` (T, 4) on ``points`` (N, 3), or that hold a
    tetrahedron's centroid (:func:`~fpm.io.meshes.voxelise.centroid_cells`: a wall thinner
    than h/2 can pass between the octants' centres)."""
    fine, _ = voxelise_tetrahedra(points, tets, spacing / 2, grid=(origin, 2 * cells))
    cx, cy, cz = (int(c) for c in cells)
    octants = fine.reshape(cx, 2, cy, 2, cz, 2).any(axis=(1, 3, 5))
    return np.asarray(octants | centroid_cells(points, tets, spacing, origin, cells), dtype=bool)


def mesh_points(mesh: Any) -> np.ndarray:
    """(N, 3) the coordinates of a meshio ``mesh``, as given (before any scale).

    Raises:
        MeshError: points that are not 3-D, or the first node with a NaN or infinite
            coordinate, by its index and coordinates.
    """
    points = np.asarray(mesh.points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"the mesh has {points.shape[-1]}-D points: a solid needs 3-D coordinates")
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if len(bad):
        raise MeshError(
            f"node {int(bad[0])} of the mesh has a non-finite coordinate {_fmt(points[bad[0]])} "
            f"({len(bad)} such node(s)): give finite coordinates, or remove the node"
        )
    return points


def positive_scale(scale: Any) -> float:
    """``scale`` as a float, or a ValueError saying it must be a finite number > 0."""
    value = float(scale)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"scale must be a finite number > 0, e.g. 0.001 for mm (got {scale!r})")
    return value


def out_of_range(cells: np.ndarray, n: int, what: str, among: str) -> None:
    """Raise :class:`MeshError` naming the first of ``cells`` (C, corners) whose node index is
    not one of the mesh's ``n`` nodes; ``what`` names the cell (e.g. ``"tetra cell"``),
    ``among`` what it is counted in (e.g. ``"in its block"``)."""
    bad = np.flatnonzero((cells < 0).any(axis=1) | (cells >= n).any(axis=1))
    if len(bad):
        c = int(bad[0])
        index = next(int(i) for i in cells[c] if not 0 <= i < n)
        raise MeshError(
            f"{what} {c} (of {len(cells)} {among}; {len(bad)} such) names node {index}, "
            f"which is not in the mesh (nodes 0..{n - 1})"
        )


def check_volume_cells(
    points: np.ndarray, volumes: list[tuple[int, np.ndarray]], names: list[str]
) -> list[str]:
    """Refuse a mesh with a degenerate (flat) volume cell; say how many are inverted.

    ``volumes``: per cell block, (corners, (C, corners) node indices) on ``points`` (N, 3), m;
    ``names`` its meshio cell type. A cell is *degenerate* when one of the tetrahedra it is
    split into (:data:`_SPLIT`) has a volume of at most
    :data:`fpm.model.tetrahedra.DEGENERATE` times its longest edge cubed (its corners on one
    plane: it holds no solid, and a 10-node element on it has no stiffness); *inverted* when its
    tetrahedra have negative volumes (numbered inside out), which is repaired (the reference's
    tetrahedra are renumbered: :func:`_reference_mesh`; the voxelisation does not depend on the
    order). Returns the notes (the repairs).

    Raises:
        MeshError: the first degenerate cell, by its index in its cell block and the reason.
    """
    from ...model.tetrahedra import DEGENERATE, TetMesh

    inverted: list[str] = []
    for (n, cells), name in zip(volumes, names, strict=True):
        if not len(cells):
            continue
        out_of_range(cells, len(points), f"{name} cell", "in its block")
        tets = cells[:, _SPLIT[n]].reshape(-1, 4)
        mesh = TetMesh(points, tets)
        volume = mesh.volumes.reshape(len(cells), -1)
        longest = mesh.longest_edges
        flat = (np.abs(volume) <= DEGENERATE * longest.reshape(len(cells), -1) ** 3).any(axis=1)
        if flat.any():
            c = int(np.flatnonzero(flat)[0])
            total = float(np.abs(volume[c]).sum())
            raise MeshError(
                f"{name} cell {c} (of {len(cells)} in its block; {int(flat.sum())} such) is "
                f"degenerate: volume {total:.3g} m^3 for its longest edge "
                f"{longest.reshape(len(cells), -1)[c].max():.3g} m, its corners (nearly) on one "
                f"plane at {_fmt(points[cells[c]].mean(axis=0))} m: it holds no solid; remove "
                "it or repair the mesh"
            )
        bad = np.flatnonzero((volume < 0).all(axis=1))
        if len(bad):
            shown = ", ".join(map(str, bad[:5].tolist())) + (", ..." if len(bad) > 5 else "")
            inverted.append(
                f"{len(bad)} {name} cells numbered inside out (negative volume: {shown}) were "
                "renumbered"
            )
    return inverted


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
    """``reference.mesh`` of the tetrahedra: used nodes only, nodes at the same point merged
    (:func:`~fpm.model.tetrahedra.merge_coincident`: else the FEM would see a crack, or two
    pieces, where the lattice sees one solid), inside-out tetrahedra renumbered, flat ones (no
    volume: e.g. from a split wedge) dropped; ``tags`` (one per tetrahedron) kept as its
    ``tags``. Of the mesh's pieces (:func:`~fpm.model.tetrahedra.lattice_pieces`, as the
    service checks a spec's mesh) only those holding one of the lattice's cell ``centres``
    (C, 3), m, are kept: the reference is the solid the lattice is (:func:`one_piece` drops
    the cells of the others), and a piece joined by less than a face would not be held, and a
    load spread onto it (:mod:`fpm.fem.loads`) could not be carried. A note in ``notes`` says
    what was left out.

    Raises:
        MeshError: two pieces hold lattice cells (they touch or overlap without sharing faces,
            or lie closer than the spacing): the lattice joins them, the FEM would not.
    """
    from ...model.tetrahedra import DEGENERATE, TetMesh, lattice_pieces, merge_coincident

    used, inverse = np.unique(tets, return_inverse=True)
    nodes, tets, merged = merge_coincident(points[used], inverse.reshape(-1, 4))
    if merged:
        notes.append(
            f"reference.mesh: merged {merged} node(s) at the same point as "
            "another (numbered twice, e.g. where two blocks or regions meet): the tetrahedra "
            "on them are joined, as the lattice's cells are"
        )
    mesh = TetMesh(nodes, tets)
    volume = mesh.volumes
    solid = np.abs(volume) > DEGENERATE * mesh.longest_edges**3
    tets = tets[solid]
    volume = volume[solid]
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    found = lattice_pieces(nodes, tets, centres)
    if len(found.cells) > 1:
        apart = found.joined_apart(nodes, tets, np.flatnonzero(solid))
        if apart:  # the lattice joins them, the FEM on the tetrahedra would not
            raise MeshError(apart)
        held = found.held
        keep = held[found.piece]
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
    from ...model.geometry import hexahedron_volumes

    notes = []
    if spacing is not None:
        notes.append(
            "the mesh is hexahedral and is used as it is (--spacing ignored; --voxelise "
            "resamples it onto a lattice)"
        )
    out_of_range(hexes, len(points), "hexahedron", "hexahedra")
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
