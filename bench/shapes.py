"""The organs the project generates (:mod:`bench.anatomy`), each with a thin part:
:func:`lobe` (a lobe tapering to an edge), :func:`hollow` (a hollow organ's closed wall),
:func:`limb` (a body with a thin tapering appendage), each a structured grid of Kuhn
tetrahedra mapped onto the shape (pure NumPy), with its analytic volume.
"""

from __future__ import annotations

from typing import Any

import meshio
import numpy as np

from bench.tet_organ import KUHN, cube_to_ball
from fpm.model.tetrahedra import signed_volumes

LONGEST = 0.2
"""Every organ's longest side, m."""


def _positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """``tets`` with the inside-out ones renumbered."""
    tets = tets.copy()
    inverted = signed_volumes(nodes[tets]) < 0
    tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
    return tets


def grid_tetrahedra(
    cells: tuple[int, int, int], keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes of the unit cube's grid of ``cells`` and (T, 4) Kuhn tetrahedra (6 per cell)
    of the cells ``keep`` (a boolean array of shape ``cells``; all by default), the unused nodes
    dropped."""
    nx, ny, nz = cells
    axes = [np.linspace(0, 1, n + 1) for n in cells]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.nonzero(np.ones(cells, bool) if keep is None else keep)
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    used, tets = np.unique(corners[:, KUHN].reshape(-1, 4), return_inverse=True)
    return grid[used], tets.reshape(-1, 4)


def _square_to_disk(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of [-1, 1]^2 onto the unit disk (smooth, one to one, the square's sides onto the
    circle)."""
    return u * np.sqrt(1 - v**2 / 2), v * np.sqrt(1 - u**2 / 2)


LOBE = {"length": LONGEST, "width": 0.12, "thick": 0.3 * LONGEST, "edge": 0.01 * LONGEST}
"""The lobe's length (x), width (y), thickness at its root and at its edge, m."""


def lobe(cells: tuple[int, int, int] = (32, 16, 4)) -> meshio.Mesh:
    """A lobe tapering to an edge: over x in [0, length] its thickness falls linearly from
    ``thick`` (30% of its length) at the root to ``edge`` (1%) at the rim, across y in
    [-width/2, width/2] it thins as 1 - (2y/width)^2 / 2; the underside is the plane z = 0
    (:data:`LOBE`)."""
    grid, tets = grid_tetrahedra(cells)
    u, v, w = grid.T
    x = LOBE["length"] * u
    y = LOBE["width"] * (v - 0.5)
    root, edge = LOBE["thick"], LOBE["edge"]
    z = w * (root + (edge - root) * u) * (1 - (2 * y / LOBE["width"]) ** 2 / 2)
    nodes = np.stack([x, y, z], axis=1)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def lobe_volume() -> float:
    """The lobe's volume, m^3: length * width * (5/6) * (thick + edge) / 2."""
    return LOBE["length"] * LOBE["width"] * 5 / 6 * (LOBE["thick"] + LOBE["edge"]) / 2


HOLLOW: dict[str, Any] = {"semi_axes": (0.1, 0.08, 0.07), "wall": 0.08}
"""The hollow organ's outer semi-axes, m, and its wall as a fraction of them (an inner
ellipsoid of semi-axes (1 - wall) times the outer's: a wall 4% of the diameter across each
axis)."""


def hollow(cells: int = 14, layers: int = 2) -> meshio.Mesh:
    """A hollow organ's closed wall (a bladder, a stomach): the shell between two ellipsoids
    (:data:`HOLLOW`), ``layers`` tetrahedra deep. The cube's grid of ``cells``^3 less its inner
    cells, each point sent along its cube-to-ball direction (:func:`bench.tet_organ.cube_to_ball`
    of its projection onto the cube's surface) to the radius its layer gives."""
    n = cells
    index = np.arange(n)
    depth = np.minimum(index, n - 1 - index)
    keep = np.minimum.outer(np.minimum.outer(depth, depth), depth) < layers
    grid, tets = grid_tetrahedra((n, n, n), keep)
    p = 2 * grid - 1
    level = np.abs(p).max(axis=1)  # 1 on the outer surface, 1 - 2 layers / n on the inner
    direction = cube_to_ball(p / level[:, None])
    inner = 1 - 2 * layers / n
    radius = 1 - HOLLOW["wall"] * (1 - level) / (1 - inner)
    nodes = direction * radius[:, None] * np.asarray(HOLLOW["semi_axes"])
    nodes -= nodes.min(axis=0)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def hollow_volume() -> float:
    """The wall's volume, m^3: 4/3 pi a b c (1 - (1 - wall)^3)."""
    a, b, c = HOLLOW["semi_axes"]
    return 4 / 3 * np.pi * a * b * c * (1 - (1 - HOLLOW["wall"]) ** 3)


LIMB = {"body": 0.11, "radius": 0.04, "end": 0.15, "tip": 0.002}
"""The limb's body length and greatest radius, the share of that radius its ends keep (as the
square root of ``end``, 0.39), and the appendage's tip radius, m (its length: the rest of
:data:`LONGEST`)."""


def limb_radius(x: np.ndarray) -> np.ndarray:
    """The limb's radius at x, m: the body over [0, body] an ellipsoid's, kept above
    sqrt(end) times its greatest at the ends, then the appendage tapering linearly to ``tip``
    at LONGEST."""
    c, r = LIMB["body"] / 2, LIMB["radius"]
    body = r * np.sqrt(np.maximum(1 - (1 - LIMB["end"]) * ((x - c) / c) ** 2, LIMB["end"]))
    join = r * np.sqrt(LIMB["end"])
    t = (x - LIMB["body"]) / (LONGEST - LIMB["body"])
    return np.where(x <= LIMB["body"], body, join + (LIMB["tip"] - join) * t)


def limb(cells: tuple[int, int] = (44, 6)) -> meshio.Mesh:
    """A body with a thin tapering appendage (a limb, a tail): a solid of revolution about the
    x axis of radius :func:`limb_radius`, ``cells[0]`` tetrahedra along it (the body's and the
    appendage's lengths split in proportion) and ``cells[1]`` across, its cross-section the
    square mapped onto the disk."""
    along, across = cells
    grid, tets = grid_tetrahedra((along, across, across))
    u, v, w = grid.T
    x = LONGEST * u
    y, z = _square_to_disk(2 * v - 1, 2 * w - 1)
    r = limb_radius(x)
    nodes = np.stack([x, r * y, r * z + LIMB["radius"]], axis=1)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def limb_volume() -> float:
    """The limb's volume, m^3: pi r^2 integrated along x (body and cone in closed form)."""
    c, r = LIMB["body"] / 2, LIMB["radius"]
    body = np.pi * r**2 * 2 * c * (1 - (1 - LIMB["end"]) / 3)
    r0, r1, length = r * np.sqrt(LIMB["end"]), LIMB["tip"], LONGEST - LIMB["body"]
    return float(body + np.pi * length * (r0**2 + r0 * r1 + r1**2) / 3)
