"""A tetrahedral organ of our own making, of any size, with well-shaped tetrahedra.

The organ ellipsoid of :mod:`bench.organ` (semi-axes 7, 4.5, 3.5 cm), meshed by mapping a grid
of ``cells`` cubes, each split into 6 tetrahedra around its diagonal (Kuhn), from the cube
[-1, 1]^3 onto the unit ball (the cube-to-sphere map
``x' = x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3)`` and its cyclic permutations: smooth, one to one,
the cube's faces onto the sphere) and scaling by the semi-axes. Unlike ``examples/lobe.vtu``
(a Delaunay mesh of surface and jittered interior points, with slivers down to 2e-5 of a
regular tetrahedron's volume-to-edge ratio) its flattest tetrahedra, at the cube's corners, keep
0.008-0.02 of it, so the 10-node reference's iterative solver needs few iterations on it and on
its refinements. ``cells=(12, 9, 8)`` gives
5,184 tetrahedra (the 5,000-tetrahedron organ of ``python -m bench refine``), ``(5, 4, 4)`` 480
(a few hundred, as public organ meshes come); an even count along z puts a layer of nodes on
the plane z = 0.
"""

from __future__ import annotations

from typing import Any

import numpy as np

SEMI_AXES = np.array([0.07, 0.045, 0.035])
"""Semi-axes of the organ ellipsoid, m (as bench/organ.py)."""
KUHN = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
"""Six tetrahedra around the diagonal 0-6 of a hexahedron (fpm.model.hexahedron order)."""


def cube_to_ball(p: np.ndarray) -> np.ndarray:
    """(N, 3) points of [-1, 1]^3 mapped onto the unit ball (module docstring)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.stack(
        [
            x * np.sqrt(1 - y**2 / 2 - z**2 / 2 + y**2 * z**2 / 3),
            y * np.sqrt(1 - z**2 / 2 - x**2 / 2 + z**2 * x**2 / 3),
            z * np.sqrt(1 - x**2 / 2 - y**2 / 2 + x**2 * y**2 / 3),
        ],
        axis=1,
    )


def organ_mesh(
    cells: tuple[int, int, int] = (12, 9, 8), semi_axes: np.ndarray = SEMI_AXES
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes, m, and (T, 4) positive tetrahedra of the organ (6 per grid cell)."""
    nx, ny, nz = cells
    axes = [np.linspace(-1, 1, n + 1) for n in cells]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    nodes = cube_to_ball(grid) * np.asarray(semi_axes)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (
        a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    )
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    tets = corners[:, KUHN].reshape(-1, 4)
    c = nodes[tets]
    volume = np.linalg.det(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]
    return nodes, tets


def quality(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) volume over longest edge cubed, relative to the regular tetrahedron's (1 = best)."""
    c = nodes[tets]
    volume = np.abs(np.linalg.det(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))) / 6
    pairs = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    longest = np.stack([np.linalg.norm(c[:, a] - c[:, b], axis=1) for a, b in pairs], 1).max(1)
    return volume / longest**3 / (1 / (6 * np.sqrt(2)))


def organ_spec(
    cells: tuple[int, int, int] = (12, 9, 8),
    spacing: float = 0.01,
    *,
    validation: bool = True,
    refine: int | str | None = "auto",
    held_below: float = 0.0,
    conforming: bool = False,
) -> dict:
    """The organ as ``fpmcal spec from-mesh`` would make it (a voxel lattice of ``spacing``, a
    cell solid when its centre lies in a tetrahedron; the tetrahedra as the reference), E 5 kPa,
    nu 0.45, held below z = ``held_below`` (m: its lower half, lying in its bed); fitted: a press
    on top (0.02 N) and a lateral pull at the top (0.01 N); validation (``validation``): a press
    off centre, a pull along y at the side, both presses at once. ``refine`` None leaves
    reference.refine out. ``conforming``: the voxels' surface nodes moved onto the mesh's
    surface, a hexahedral ``mesh`` geometry (:func:`fpm.io.meshes.conform_spec`, what
    ``fpmcal spec from-mesh --conform`` makes; the held box keeps its nodes).

    How fast a uniformly refined reference converges depends on the supports (measured with
    ``python -m bench refine``, 480 tetrahedra, the worst case per level): held below the
    equator, whose plane is a layer of the mesh's nodes and meets the surface at right angles,
    it changes by 22.7 / 5.7 / 1.5% from one refinement to the next; the 360 tetrahedra of cells
    (5, 4, 3) held below z = -25 mm, which no mesh face follows (each level holds the nodes it
    has there, a staircase closer to the plane) and which meets the surface obliquely (a
    stronger singular line), by 12.4 / 12.3% after the first refinement: no better.
    """
    from fpm.model.tetrahedra import TetMesh

    nodes, tets = organ_mesh(cells)
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    counts = np.ceil((hi - lo) / spacing - 1e-9).astype(int)
    origin = (lo + hi) / 2 - counts * spacing / 2
    grid = np.stack(np.meshgrid(*map(np.arange, counts), indexing="ij"), axis=-1)
    centres = origin + spacing * (grid.reshape(-1, 3) + 0.5)
    inside = TetMesh(nodes, tets).locate(centres).distance == 0
    top = [0.0, 0.0, float(hi[2])]

    def press(name: str, *points: list[float], vector: list[float]) -> dict:
        return {
            "name": name,
            "forces": [{"nearest": p, "vector": vector} for p in points],
        }

    spec: dict = {
        "name": f"tetrahedral organ, {len(tets)} tetrahedra",
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {
            "type": "voxels",
            "occupancy": inside.reshape(*counts).tolist(),
            "spacing": [spacing] * 3,
            "origin": origin.tolist(),
        },
        "fixed": [{"box": [[-1, -1, -1], [1, 1, held_below]]}],
        "load_cases": [
            press("press top", top, vector=[0, 0, -0.02]),
            press("lateral", top, vector=[0.01, 0, 0]),
        ],
        "reference": {"mesh": {"nodes": nodes.tolist(), "tetrahedra": tets.tolist()}},
    }
    if validation:
        spec["validation_cases"] = [
            press("press off centre", [0.03, 0.0, 0.03], vector=[0, 0, -0.02]),
            press("lateral y", [0.0, 0.045, 0.015], vector=[0, 0.01, 0]),
            press("two presses", top, [0.03, 0.0, 0.03], vector=[0, 0, -0.01]),
        ]
    if refine is not None:
        spec["reference"]["refine"] = refine
    if conforming:
        from fpm.io.meshes import conform_spec

        spec = conform_spec(spec)[0]
    return spec


KIDNEY_AXES = np.array([0.06, 0.032, 0.026])
"""Semi-axes of the kidney-like organ before it is bent and tapered, m."""


def kidney_mesh(cells: tuple[int, int, int] = (6, 4, 3)) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes, m, and (T, 4) positive tetrahedra of a second organ, unlike the first: a
    bean 12 cm long, tapered to 0.55 of its thickness at x = +6 cm (its thin end) and bent
    about z by 1.5 cm at its ends (a concave side, like a kidney's hilum), meshed as
    :func:`organ_mesh` (``cells`` (6, 4, 3): 432 tetrahedra, an odd count along z so that no
    node layer lies on z = 0). Every tetrahedron keeps a positive volume (checked)."""
    nodes, tets = organ_mesh(cells, KIDNEY_AXES)
    x = nodes[:, 0] / KIDNEY_AXES[0]  # -1 .. 1 along the bean
    taper = 1.0 - 0.225 * (x + 1.0)  # 1 at x = -6 cm, 0.55 at +6 cm
    bent = nodes.copy()
    bent[:, 1] = nodes[:, 1] * taper + 0.015 * x**2
    bent[:, 2] = nodes[:, 2] * taper
    c = bent[tets]
    volume = np.linalg.det(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))
    assert np.all(volume > 0)
    return bent, tets


ORGANS: dict[str, dict[str, Any]] = {
    "organ": {
        "mesh": lambda: organ_mesh((5, 4, 4)),
        "held": "box:-1,-1,-1:1,1,0",  # its lower half, lying in its bed
        "fitted": [("press top", [0.0, 0.0, 1.0], [0, 0, -0.02]),
                   ("lateral", [0.0, 0.0, 1.0], [0.01, 0, 0])],
        "validation": [("press off centre", [0.03, 0.0, 0.04], [0, 0, -0.02]),
                       ("lateral y", [0.0, 0.05, 0.015], [0, 0.01, 0]),
                       ("two presses", [[0.0, 0.0, 1.0], [0.03, 0.0, 0.04]], [0, 0, -0.01])],
    },
    "kidney": {
        "mesh": kidney_mesh,
        "held": "box:0.045,-1,-1:1,1,1",  # the thin end, its last 1.5 cm
        "fitted": [("press middle", [0.0, 0.0, 0.04], [0, 0, -0.01]),
                   ("pull far end", [-0.07, 0.015, 0.0], [0, 0.005, 0])],
        "validation": [("press near end", [-0.035, 0.005, 0.04], [0, 0, -0.01]),
                       ("push convex side", [-0.01, -0.05, 0.0], [0, 0.005, 0]),
                       ("press and pull", [[0.0, 0.0, 0.04], [-0.07, 0.015, 0.0]],
                        [0, 0.0035, -0.0035])],
    },
}  # fmt: skip
"""The organs of ``python -m bench.bench_refine organs``: the bench's (480 tetrahedra, its lower
half held) and a kidney-like bean (432 tetrahedra, held at its thin end: a cantilever), each
with two fitted and three validation cases; every force at a point of the surface (the point
nearest the aim given here, m, so an aim sits just off the surface where the force goes: an aim
far away would take the surface's extreme point; an aim of several points puts one force at
each), N."""


def surface_spec(
    organ: str, spacing: float, refine: int | str = "auto", lattice: str = "conforming"
) -> dict:
    """``organ`` (a key of :data:`ORGANS`) as ``spec_from_mesh`` makes it with the defaults (the
    conforming lattice of ``spacing``, m; E 5 kPa, nu 0.45) and its forces at points of the
    mesh's surface (``point:``, spread over their surface cells' nodes), the validation cases
    added in the same form; ``reference.refine`` = ``refine``; ``lattice`` as
    ``spec_from_mesh``'s (``"voxels"`` for the staircase, to compare)."""
    import meshio

    from fpm.io.meshes import spec_from_mesh
    from fpm.model.tetrahedra import TetMesh

    made = ORGANS[organ]
    nodes, tets = made["mesh"]()

    def forces(aim: list, vector: list[float]) -> str:
        aims = np.atleast_2d(np.asarray(aim, dtype=float))
        at = TetMesh(nodes, tets).nearest_on_boundary(aims)[1]
        return ";".join(
            "point:" + ",".join(f"{v:.6f}" for v in p) + ":" + ",".join(map(str, vector))
            for p in at
        )

    spec, _ = spec_from_mesh(
        meshio.Mesh(nodes, [("tetra", tets)]),
        fix=[made["held"]],
        forces=[forces(aim, vector) for _, aim, vector in made["fitted"]],
        youngs_modulus=5e3,
        poisson_ratio=0.45,
        density=1040.0,
        spacing=spacing,
        name=f"{organ}, {len(tets)} tetrahedra",
        lattice=lattice,
    )
    for case, (name, _, _) in zip(spec["load_cases"], made["fitted"], strict=True):
        case["name"] = name
    from fpm.io.meshes import parse_force

    spec["validation_cases"] = [
        {"name": name, "forces": parse_force(forces(aim, vector))}
        for name, aim, vector in made["validation"]
    ]
    spec["reference"]["refine"] = refine
    return spec
