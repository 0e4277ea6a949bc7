"""Mesh formats users have that meshio does not read: Gmsh legacy v1 (``$NOD``/``$ELM``) and
legacy VTK POLYDATA surfaces (ASCII). Both become a ``meshio.Mesh`` for
:func:`fpm.io.meshes.geometry_from_mesh`; a file that breaks the format is a
:class:`fpm.io.errors.MeshError` naming the line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .errors import MeshError

GMSH1_TYPES = {2: ("triangle", 3), 3: ("quad", 4), 4: ("tetra", 4), 5: ("hexahedron", 8),
               6: ("wedge", 6), 7: ("pyramid", 5)}  # fmt: skip
"""Gmsh v1 element types read (lines and points, types 1 and 15, are skipped)."""


def read_legacy(path: Path, kind: str) -> Any:
    """The mesh in ``path`` of legacy ``kind`` (``"gmsh1"`` or ``"polydata"``)."""
    try:
        tokens = path.read_text(encoding="latin-1").split()
        return read_gmsh1(tokens) if kind == "gmsh1" else read_polydata(tokens)
    except (ValueError, IndexError, KeyError) as e:
        what = "Gmsh v1" if kind == "gmsh1" else "VTK POLYDATA"
        raise MeshError(f"{path}: not a readable {what} file ({e})") from None


def read_gmsh1(tokens: list[str]) -> Any:
    """Gmsh v1: ``$NOD n`` then ``id x y z`` lines, ``$ENDNOD``; ``$ELM n`` then
    ``id type reg-phys reg-elem n-nodes node...`` lines, ``$ENDELM``."""
    import meshio

    at = tokens.index("$NOD")
    count = int(tokens[at + 1])
    rows = np.asarray(tokens[at + 2 : at + 2 + 4 * count], dtype=float).reshape(count, 4)
    if tokens[at + 2 + 4 * count] != "$ENDNOD":
        raise ValueError("$NOD section does not end with $ENDNOD where its count says")
    index = {int(i): n for n, i in enumerate(rows[:, 0])}
    at = tokens.index("$ELM")
    count, pos = int(tokens[at + 1]), at + 2
    cells: dict[str, list[list[int]]] = {}
    for _ in range(count):
        kind, n = int(tokens[pos + 1]), int(tokens[pos + 4])
        nodes = [index[int(t)] for t in tokens[pos + 5 : pos + 5 + n]]
        pos += 5 + n
        if kind in GMSH1_TYPES:
            name, size = GMSH1_TYPES[kind]
            if len(nodes) != size:
                raise ValueError(f"element of type {kind} with {len(nodes)} nodes, not {size}")
            cells.setdefault(name, []).append(nodes)
    if tokens[pos] != "$ENDELM":
        raise ValueError("$ELM section does not end with $ENDELM where its count says")
    return meshio.Mesh(rows[:, 1:], [(k, np.asarray(v, dtype=np.int64)) for k, v in cells.items()])


def read_polydata(tokens: list[str]) -> Any:
    """ASCII legacy VTK POLYDATA: ``POINTS n type`` then 3n numbers; ``POLYGONS n size`` (or
    ``TRIANGLE_STRIPS``) then per polygon its vertex count and vertices. Polygons are split
    into triangles (a fan from the first vertex)."""
    import meshio

    upper = [t.upper() for t in tokens]
    if "BINARY" in upper[:12]:
        raise ValueError("binary VTK is not read: save it as ASCII")
    at = upper.index("POINTS")
    count = int(tokens[at + 1])
    points = np.asarray(tokens[at + 3 : at + 3 + 3 * count], dtype=float).reshape(count, 3)
    triangles: list[list[int]] = []
    for section in ("POLYGONS", "TRIANGLE_STRIPS"):
        if section not in upper:
            continue
        at = upper.index(section)
        polygons, pos = int(tokens[at + 1]), at + 3
        for _ in range(polygons):
            n = int(tokens[pos])
            vertex = [int(t) for t in tokens[pos + 1 : pos + 1 + n]]
            pos += 1 + n
            if section == "POLYGONS":
                triangles += [[vertex[0], vertex[i], vertex[i + 1]] for i in range(1, n - 1)]
            else:  # a strip: alternate the orientation
                triangles += [
                    [vertex[i], vertex[i + 1], vertex[i + 2]] if i % 2 == 0
                    else [vertex[i + 1], vertex[i], vertex[i + 2]]
                    for i in range(n - 2)
                ]  # fmt: skip
    if not triangles:
        raise ValueError("no POLYGONS or TRIANGLE_STRIPS: no surface to read")
    if max(max(t) for t in triangles) >= count or min(min(t) for t in triangles) < 0:
        raise ValueError("a polygon names a point that does not exist")
    return meshio.Mesh(points, [("triangle", np.asarray(triangles, dtype=np.int64))])
