"""Writes examples/lobe.vtu: a tetrahedral mesh of the organ ellipsoid of bench/organ.py.

Semi-axes 7, 4.5, 3.5 cm, 1,567 nodes and 7,547 tetrahedra (SciPy's Delaunay of evenly spread
surface points and a jittered interior grid): a stand-in for an organ exported from a
segmentation tool, to try `fpmcal spec from-mesh` on (docs/tutorial/organ-mesh.md).
Run: .venv/bin/python examples/lobe.py
"""

from pathlib import Path

import meshio
import numpy as np
from scipy.spatial import Delaunay

SEMI_AXES = np.array([0.07, 0.045, 0.035])


def main() -> None:
    rng = np.random.default_rng(13)
    n = 900  # surface points on a Fibonacci sphere
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    surface = np.stack(
        [np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1
    )
    grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 13)] * 3, indexing="ij"), -1).reshape(-1, 3)
    grid += rng.uniform(-0.02, 0.02, grid.shape)
    points = np.vstack([surface, grid[np.linalg.norm(grid, axis=1) < 0.9]]) * SEMI_AXES
    tetrahedra = Delaunay(points).simplices.astype(np.int32)
    path = Path(__file__).with_name("lobe.vtu")
    meshio.write(path, meshio.Mesh(points, [("tetra", tetrahedra)]))
    print(f"wrote {path}: {len(points)} nodes, {len(tetrahedra)} tetrahedra")


if __name__ == "__main__":
    main()
