"""The lattice's size in nodes: the spacing that voxelises a mesh into about N nodes.

A real-time budget is a node count (a simulator steps so many nodes per frame), not a
spacing; ``fpmcal spec from-mesh --nodes N`` and ``spec_from_mesh(..., nodes=N)`` take it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import MeshError
from .geometry import MeshGeometry, geometry_from_mesh, mesh_points, positive_scale
from .graded import graded_lattice
from .voxelise import _fmt

TRIES = 8
""":func:`spacing_for_nodes` voxelises the mesh at most this many times."""
CLOSE = 0.02
"""... and stops at a lattice within this fraction of the node count asked."""
NEAR = 0.1
"""When the nearest of those is further than this fraction from the count asked (a graded
lattice's count jumps as its refined parts come and go with the spacing), spacings within a
factor :data:`SCAN` of it are tried too, :data:`SCAN_STEPS` a side."""
SCAN = 1.2
SCAN_STEPS = 4


def lattice_nodes(occupancy: Any) -> int:
    """The nodes of the voxel lattice of ``occupancy`` (cx, cy, cz) bool: the corners of its
    occupied cells."""
    occ = np.asarray(occupancy, dtype=bool)
    cx, cy, cz = occ.shape
    corners = np.zeros((cx + 1, cy + 1, cz + 1), dtype=bool)
    for di, dj, dk in np.ndindex(2, 2, 2):
        corners[di : di + cx, dj : dj + cy, dk : dk + cz] |= occ
    return int(corners.sum())


def graded_nodes(made: MeshGeometry) -> int:
    """The nodes of the lattice ``made`` becomes on the conforming path: its voxels with their
    parts one cell thick refined (:func:`~fpm.io.meshes.graded.graded_lattice`) where it has
    tetrahedra to refine from, else its voxels' (:func:`lattice_nodes`)."""
    if made.tetrahedra is None:
        return lattice_nodes(made.geometry["occupancy"])
    g = made.geometry
    lattice = graded_lattice(
        np.asarray(g["occupancy"], dtype=bool),
        np.asarray(g["origin"], dtype=float),
        float(min(g["spacing"])),
        np.asarray(made.tetrahedra["nodes"], dtype=float),
        np.asarray(made.tetrahedra["tetrahedra"]),
    )
    return len(lattice.nodes)


def spacing_for_nodes(
    mesh: Any, nodes: int, counter: Callable[[MeshGeometry], int] | None = None, **options: Any
) -> tuple[float, MeshGeometry]:
    """The spacing h (m, three significant digits) whose lattice of ``mesh`` (a
    ``meshio.Mesh``) has the node count nearest ``nodes``, and that lattice
    (:func:`geometry_from_mesh` with ``options``: scale, connectivity, voxelise, planes).
    ``counter`` gives a lattice's node count (default: its voxels', :func:`lattice_nodes`;
    :func:`graded_nodes` for the conforming lattice, refinement included).

    The count goes as 1 / h^3: from the guess of the mesh's bounding box half full, each try
    scales h by (count / nodes)^(1/3), until a lattice is within :data:`CLOSE` of ``nodes`` or
    :data:`TRIES` are made (the count moves in steps as whole layers of cells come and go; the
    nearest wins). A note says what was asked and what was found.

    Raises:
        ValueError: ``nodes`` under 8 (one cell).
        MeshError: a hexahedral mesh (used as it is: give ``voxelise``), or one the
            voxeliser refuses.
    """
    if not nodes >= 8:
        raise ValueError(f"nodes must be at least 8, one cell (got {nodes})")
    points = mesh_points(mesh) * positive_scale(options.get("scale", 1.0))
    if not len(points):
        raise MeshError("the mesh has no nodes: it holds no solid to voxelise")
    extent = np.ptp(points, axis=0)
    if not np.all(extent > 0):
        flat = "xyz"[int(np.flatnonzero(~(extent > 0))[0])]
        raise MeshError(
            f"the mesh has no extent along {flat} (its nodes span {_fmt(points.min(axis=0))} to "
            f"{_fmt(points.max(axis=0))} m): it holds no solid to voxelise"
        )
    h = _rounded((0.5 * float(np.prod(extent)) / nodes) ** (1 / 3))
    tried: dict[float, tuple[int, MeshGeometry]] = {}
    for _ in range(TRIES):
        made = geometry_from_mesh(mesh, spacing=h, **options)
        if made.geometry.get("type") != "voxels":
            raise MeshError(
                "a hexahedral mesh is used as it is, at its own node count: nodes chooses the "
                "spacing of a voxelised lattice (give voxelise, --voxelise, to resample it)"
            )
        if not lattice_nodes(made.geometry["occupancy"]):  # no cell centre inside: far too coarse
            h = _rounded(h / 2)
            continue
        count = (counter or _voxel_count)(made)
        tried[h] = (count, made)
        if abs(count / nodes - 1) <= CLOSE:
            break
        h = _rounded(h * (count / nodes) ** (1 / 3))
        if h in tried:
            break
    if not tried:
        raise MeshError(f"no spacing down to {h:.3g} m puts a lattice cell inside the mesh")
    h = min(tried, key=lambda s: abs(math.log(tried[s][0] / nodes)))
    if abs(tried[h][0] / nodes - 1) > NEAR:  # the count jumps (refined parts come and go)
        for factor in np.geomspace(1 / SCAN, SCAN, 2 * SCAN_STEPS + 1):
            s = _rounded(h * factor)
            if s not in tried:
                made = geometry_from_mesh(mesh, spacing=s, **options)
                if lattice_nodes(made.geometry["occupancy"]):
                    tried[s] = ((counter or _voxel_count)(made), made)
        h = min(tried, key=lambda s: abs(math.log(tried[s][0] / nodes)))
    count, made = tried[h]
    made.notes.insert(
        0,
        f"spacing h = {h:.3g} m for about {nodes:,} nodes: the lattice has {count:,} "
        f"({len(tried)} spacing(s) tried)",
    )
    return h, made


def _voxel_count(made: MeshGeometry) -> int:
    return lattice_nodes(made.geometry["occupancy"])


def _rounded(h: float) -> float:
    """``h`` to three significant digits (a spacing a spec can show as it is)."""
    return float(f"{h:.3g}")
