"""A voxelised soft "organ": the ellipsoid the organ benchmarks and tests measure on.

Semi-axes 7, 4.5, 3.5 cm (centre at the origin), soft tissue (E = 5 kPa, nu = 0.45, 1040 kg/m^3),
voxelised at spacing h (a cell is solid when its centre lies inside), the bottom centimetre
fixed, and three load cases at the top: a press at the top node, a press at a top node off
centre, and a lateral (shear) force at the top node. h = 10 mm gives about 750 nodes, 5 mm about
4,600, 3 mm about 20,000.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fpm.model.geometry import voxel_mesh
from fpm.model.spec import VoxelGeometry

SEMI_AXES = (0.07, 0.045, 0.035)


def ellipsoid_spec(
    h: float,
    *,
    youngs_modulus: float = 5e3,
    press: float = 0.02,
    lateral: float = 0.01,
    connectivity: str = "full",
    validation: bool = False,
    **settings: Any,
) -> dict[str, Any]:
    """The organ's problem spec at spacing ``h`` (m); forces in N; ``settings`` go into
    the spec's top level (e.g. ``fpm={...}``, ``annealing={...}``). ``validation`` adds three
    validation cases the fit never sees: the lateral force along y (another direction), a
    press at a top node off centre along y (another point), and the two presses at once."""
    a = np.asarray(SEMI_AXES)
    cells = np.ceil(2 * a / h).astype(int)
    origin = -cells * h / 2
    centres = [origin[i] + h * (np.arange(cells[i]) + 0.5) for i in range(3)]
    x, y, z = np.meshgrid(*centres, indexing="ij")
    occupancy = (x / a[0]) ** 2 + (y / a[1]) ** 2 + (z / a[2]) ** 2 <= 1.0
    geometry = VoxelGeometry(
        occupancy=occupancy.tolist(),
        spacing=(h, h, h),
        origin=tuple(origin.tolist()),
        connectivity=connectivity,  # type: ignore[arg-type]
    )
    nodes, _ = voxel_mesh(geometry)
    bottom = nodes[:, 2].min()

    def top_node(px: float, py: float) -> list[float]:
        """The highest node of the column of nodes nearest (px, py)."""
        dxy = np.hypot(nodes[:, 0] - px, nodes[:, 1] - py)
        column = nodes[dxy <= dxy.min() + 1e-9 * h]
        return column[np.argmax(column[:, 2])].tolist()

    top, off = top_node(0.0, 0.0), top_node(0.4 * a[0], 0.0)
    side = top_node(0.0, 0.4 * a[1])
    if validation:
        settings["validation_cases"] = [
            {"name": "lateral y top", "forces": [{"at": top, "vector": [0, lateral, 0]}]},
            {"name": "press off centre y", "forces": [{"at": side, "vector": [0, 0, -press]}]},
            {
                "name": "press top and off centre",
                "forces": [
                    {"at": top, "vector": [0, 0, -press / 2]},
                    {"at": off, "vector": [0, 0, -press / 2]},
                ],
            },
        ]
    return {
        "name": f"soft ellipsoid h={h * 1e3:g} mm",
        "material": {"youngs_modulus": youngs_modulus, "poisson_ratio": 0.45, "density": 1040},
        "geometry": geometry.model_dump(),
        "fixed": [{"box": [[-1, -1, bottom - h], [1, 1, bottom + 0.01 + 1e-9]]}],
        "load_cases": [
            {"name": "press top", "forces": [{"at": top, "vector": [0, 0, -press]}]},
            {"name": "press off centre", "forces": [{"at": off, "vector": [0, 0, -press]}]},
            {"name": "lateral top", "forces": [{"at": top, "vector": [lateral, 0, 0]}]},
        ],
        **settings,
    }


def ellipsoid_tetrahedra(h: float, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A tetrahedral mesh of the organ's ellipsoid, node spacing about ``h`` (m): nodes (N, 3),
    m, and tetrahedra (T, 4) of positive volume. Delaunay (scipy) of a jittered grid inside the
    ellipsoid and of points on its surface (a Fibonacci spiral mapped onto it), slivers (volume
    under 1e-3 of the longest edge cubed) dropped, unused nodes removed. h = 4 mm gives about
    50,000 tetrahedra."""
    from scipy.spatial import Delaunay

    from fpm.model.tetrahedra import TetMesh

    a = np.asarray(SEMI_AXES)
    rng = np.random.default_rng(seed)
    axes = [np.arange(-a[i] + h / 2, a[i], h) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid + rng.uniform(-0.15 * h, 0.15 * h, grid.shape)
    r = np.sqrt(((grid / a) ** 2).sum(axis=1))
    inner = grid[r < 1 - 0.6 * h / a.min()]
    # Surface points about h apart: area of the ellipsoid (Thomsen's approximation) / h^2.
    p = 1.6075
    area = (
        4 * np.pi * (((a[0] * a[1]) ** p + (a[0] * a[2]) ** p + (a[1] * a[2]) ** p) / 3) ** (1 / p)
    )
    n = int(area / h**2 * 1.15)
    k = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / n), np.pi * (1 + 5**0.5) * k
    unit = np.stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
    )
    points = np.concatenate([inner, unit * a])
    tets = Delaunay(points).simplices.astype(np.int64)
    mesh = TetMesh(points, tets)
    solid = np.abs(mesh.volumes) > 1e-3 * mesh.longest_edges**3
    tets, volume = tets[solid], mesh.volumes[solid]
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    used, inverse = np.unique(tets, return_inverse=True)
    return points[used], inverse.reshape(-1, 4)
