"""The lattice's size in nodes: the spacing that voxelises a mesh into about N nodes.

A real-time budget is a node count (a simulator steps so many nodes per frame), not a
spacing; ``fpmcal spec from-mesh --nodes N`` and ``spec_from_mesh(..., nodes=N)`` take it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import MeshError
from .geometry import MeshGeometry, geometry_from_mesh, mesh_points, positive_scale
from .voxelise import _fmt

TRIES = 8
""":func:`spacing_for_nodes` voxelises the mesh at most this many times."""
CLOSE = 0.02
"""... and stops at a lattice within this fraction of the node count asked."""


def lattice_nodes(occupancy: Any) -> int:
    """The nodes of the voxel lattice of ``occupancy`` (cx, cy, cz) bool: the corners of its
    occupied cells."""
    occ = np.asarray(occupancy, dtype=bool)
    cx, cy, cz = occ.shape
    corners = np.zeros((cx + 1, cy + 1, cz + 1), dtype=bool)
    for di, dj, dk in np.ndindex(2, 2, 2):
        corners[di : di + cx, dj : dj + cy, dk : dk + cz] |= occ
    return int(corners.sum())


def spacing_for_nodes(mesh: Any, nodes: int, **options: Any) -> tuple[float, MeshGeometry]:
    """The spacing h (m, three significant digits) whose lattice of ``mesh`` (a
    ``meshio.Mesh``) has the node count nearest ``nodes``, and that lattice
    (:func:`geometry_from_mesh` with ``options``: scale, connectivity, voxelise, planes).

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
        count = lattice_nodes(made.geometry["occupancy"])
        if count == 0:  # no cell centre inside: far too coarse
            h = _rounded(h / 2)
            continue
        tried[h] = (count, made)
        if abs(count / nodes - 1) <= CLOSE:
            break
        h = _rounded(h * (count / nodes) ** (1 / 3))
        if h in tried:
            break
    if not tried:
        raise MeshError(f"no spacing down to {h:.3g} m puts a lattice cell inside the mesh")
    h = min(tried, key=lambda s: abs(math.log(tried[s][0] / nodes)))
    count, made = tried[h]
    made.notes.insert(
        0,
        f"spacing h = {h:.3g} m for about {nodes:,} nodes: the lattice has {count:,} "
        f"({len(tried)} spacing(s) tried)",
    )
    return h, made


def _rounded(h: float) -> float:
    """``h`` to three significant digits (a spacing a spec can show as it is)."""
    return float(f"{h:.3g}")
