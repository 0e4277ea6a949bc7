"""Geometry: one solid, three ways to describe it (box, explicit mesh, voxels), the same springs
and masses; spring counts of the three connectivities in closed form; lumped mass sums to
density x volume; h is the lattice spacing."""

from __future__ import annotations

from itertools import product
from typing import Any

import numpy as np
import pytest
from helpers_fpm import MATERIAL, box_spec, network_spec

import fpm
from fpm.model.geometry import hexahedron_volumes
from fpm.model.stiffness import continuum_start

RHO = MATERIAL["density"]

CORNERS = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
"""Offsets of the 8 corners of a lattice cell in hexahedron order (written out here, not taken
from fpm.model.hexahedron, so that the mesh below is built independently of the code under test)."""


def cells_mesh(
    cells: list[tuple[int, ...]], spacing: np.ndarray, rng: np.random.Generator
) -> dict[str, Any]:
    """Mesh geometry of the given lattice cells, with the nodes listed in a random order."""
    points = sorted({tuple(np.add(c, o)) for c in cells for o in CORNERS})
    perm = rng.permutation(len(points))
    where = {points[p]: n for n, p in enumerate(perm)}
    nodes = [list(np.multiply(points[p], spacing)) for p in perm]
    hexahedra = [[where[tuple(np.add(c, o))] for o in CORNERS] for c in cells]
    return {"type": "mesh", "nodes": nodes, "hexahedra": hexahedra}


def solid_of(geometry: dict[str, Any]) -> fpm.Problem:
    """A problem around ``geometry``: no fixed nodes, one force on node 0."""
    spec = box_spec((2, 2, 2), fixed=[], forces=[{"node": 0, "vector": [0, 0, 1.0]}])
    spec["geometry"] = geometry
    return fpm.load_problem(spec)


def key(point: np.ndarray, h: np.ndarray) -> tuple[int, ...]:
    """A lattice point as integers (node coordinates compared exactly, whatever the node order)."""
    return tuple(int(v) for v in np.rint(point / h))


def spring_set(problem: fpm.Problem, h: np.ndarray) -> set[frozenset[tuple[int, ...]]]:
    """The springs as unordered pairs of lattice points."""
    x = problem.nodes
    return {frozenset((key(x[a], h), key(x[b], h))) for a, b in problem.solid.springs}


def mass_map(problem: fpm.Problem, h: np.ndarray) -> dict[tuple[int, ...], float]:
    return {key(p, h): m for p, m in zip(problem.nodes, problem.solid.masses, strict=True)}


def closed_form_counts(n: int) -> dict[str, int]:
    """Springs on a box of n x n x n nodes (m = n - 1 cells per axis).

    Edges: 3 directions x n^2 lines x m springs. Face diagonals: 3 plane orientations x n planes
    x m^2 squares x 2. Body diagonals: m^3 cubes x 4.
    """
    m = n - 1
    edges, faces, bodies = 3 * n * n * m, 6 * n * m * m, 4 * m**3
    return {"axis": edges, "axis+face": edges + faces, "full": edges + faces + bodies}


# --- box vs mesh vs voxels ---------------------------------------------------------------


@pytest.mark.parametrize("connectivity", ["axis", "axis+face", "full"])
def test_box_mesh_and_voxels_give_the_same_solid(connectivity: str):
    shape = (3, 4, 5)
    spacing = np.array([0.01, 0.02, 0.015])  # unequal: a transposed axis would show
    cells = list(product(*(range(n - 1) for n in shape)))
    box = fpm.load_problem(box_spec(shape, tuple(spacing), connectivity=connectivity))
    mesh = solid_of(
        {**cells_mesh(cells, spacing, np.random.default_rng(1)), "connectivity": connectivity}
    )
    voxels = solid_of(
        {
            "type": "voxels",
            "occupancy": np.ones([n - 1 for n in shape], dtype=bool).tolist(),
            "spacing": spacing.tolist(),
            "connectivity": connectivity,
        }
    )
    reference = spring_set(box, spacing)
    assert len(reference) == len(box.solid.springs)  # each node pair once
    masses = mass_map(box, spacing)
    for other in (mesh, voxels):
        assert other.n_nodes == box.n_nodes == np.prod(shape)
        assert spring_set(other, spacing) == reference
        assert len(other.solid.springs) == len(reference)
        other_masses = mass_map(other, spacing)
        assert other_masses.keys() == masses.keys()
        for p, m in masses.items():
            assert other_masses[p] == pytest.approx(m, rel=1e-12)
        assert np.allclose(np.sort(other.rest_lengths), np.sort(box.rest_lengths), rtol=1e-12)
        assert other.h == pytest.approx(box.h)


def test_box_elements_are_the_cells_of_the_lattice():
    shape, h = (3, 4, 5), 0.01
    box = fpm.load_problem(box_spec(shape, h))
    hexahedra = box.solid.elements()
    assert hexahedra.shape == (2 * 3 * 4, 8)
    x = box.nodes[hexahedra]  # (H, 8, 3)
    # Every hexahedron is a cell: its corners sit at its first corner + h * CORNERS.
    assert np.allclose(x - x[:, :1], h * np.asarray(CORNERS)[None], atol=1e-15)
    assert np.allclose(hexahedron_volumes(box.nodes, hexahedra), h**3, rtol=1e-12)


def test_voxel_l_shape_matches_the_same_cells_as_a_mesh():
    """A non-convex solid: three of the four cells of a 2x2x1 block."""
    spacing = np.array([0.01, 0.01, 0.02])
    occupancy = [[[True], [True]], [[True], [False]]]  # cell (1, 1, 0) empty
    cells = [(0, 0, 0), (0, 1, 0), (1, 0, 0)]
    voxels = solid_of({"type": "voxels", "occupancy": occupancy, "spacing": spacing.tolist()})
    mesh = solid_of(cells_mesh(cells, spacing, np.random.default_rng(2)))
    assert voxels.n_nodes == mesh.n_nodes == 16  # (9 - 1) lattice points x 2 layers
    assert spring_set(voxels, spacing) == spring_set(mesh, spacing)
    assert mass_map(voxels, spacing) == pytest.approx(mass_map(mesh, spacing), rel=1e-12)
    # full connectivity: 3 cells x 28 pairs, minus the pairs on the 2 shared faces (6 each).
    assert len(voxels.solid.springs) == 3 * 28 - 2 * 6
    assert voxels.solid.masses.sum() == pytest.approx(RHO * 3 * np.prod(spacing), rel=1e-12)


# --- spring counts ---------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 4, 6])
@pytest.mark.parametrize("connectivity", ["axis", "axis+face", "full"])
def test_spring_counts_on_an_n_cubed_box(n: int, connectivity: str):
    h = 0.01
    expected = closed_form_counts(n)[connectivity]
    box = fpm.load_problem(box_spec((n, n, n), h, connectivity=connectivity))
    springs = box.solid.springs
    assert len(springs) == expected
    assert np.all(springs[:, 0] < springs[:, 1])
    assert len(np.unique(springs, axis=0)) == expected
    # By family: edges have length h, face diagonals h sqrt2, body diagonals h sqrt3.
    m = n - 1
    family = np.rint((box.rest_lengths / h) ** 2).astype(int)  # 1, 2 or 3
    assert np.allclose(box.rest_lengths, h * np.sqrt(family), rtol=1e-12)
    counts = np.bincount(family, minlength=4)[1:]
    want = {"axis": [3 * n * n * m, 0, 0], "axis+face": [3 * n * n * m, 6 * n * m * m, 0]}
    assert counts.tolist() == want.get(connectivity, [3 * n * n * m, 6 * n * m * m, 4 * m**3])
    # The mesh path (springs from hexahedra) counts the same.
    cells = list(product(range(m), repeat=3))
    mesh = solid_of(
        {
            **cells_mesh(cells, np.full(3, h), np.random.default_rng(n)),
            "connectivity": connectivity,
        }
    )
    assert len(mesh.solid.springs) == expected


def test_full_connectivity_on_a_box_is_the_26_neighbour_lattice():
    n = 5
    box = fpm.load_problem(box_spec((n, n, n), 0.01, connectivity="full"))
    degree = np.bincount(box.solid.springs.ravel(), minlength=box.n_nodes).reshape(n, n, n)
    assert np.all(degree[1:-1, 1:-1, 1:-1] == 26)
    assert degree[0, 0, 0] == 7  # a corner: the other 7 corners of its one cell


# --- masses and h ----------------------------------------------------------------------


def test_box_lumped_masses():
    """Each cell gives 1/8 of its mass to each corner: a node gets 1/8 per cell it touches."""
    shape, h = (4, 5, 6), 0.01
    box = fpm.load_problem(box_spec(shape, h))
    cell = RHO * h**3
    assert box.solid.masses.sum() == pytest.approx(RHO * 3 * 4 * 5 * h**3, rel=1e-12)
    masses = box.solid.masses.reshape(shape[::-1])  # [k, j, i]
    assert masses[0, 0, 0] == pytest.approx(cell / 8)
    assert masses[0, 0, 1] == pytest.approx(cell / 4)
    assert masses[0, 1, 1] == pytest.approx(cell / 2)
    assert masses[1, 1, 1] == pytest.approx(cell)


def test_lumped_mass_of_a_parallelepiped_and_a_frustum():
    """density x volume for non-cubic hexahedra: a sheared cell (volume |det A|) and a square
    frustum with bases 2x2 and 1x1 and height 1 (volume (4 + 1 + 2) / 3; its faces are planar,
    so the trilinear map fills it exactly)."""
    a = np.array([[0.02, 0.0, 0.0], [0.005, 0.01, 0.0], [0.003, -0.004, 0.03]])  # rows: edges
    sheared = np.asarray(CORNERS, dtype=float) @ a
    frustum = np.array(
        [
            [0, 0, 0],
            [2, 0, 0],
            [2, 2, 0],
            [0, 2, 0],
            [0.5, 0.5, 1],
            [1.5, 0.5, 1],
            [1.5, 1.5, 1],
            [0.5, 1.5, 1],
        ]
    )
    for nodes, volume in ((sheared, abs(np.linalg.det(a))), (frustum, 7 / 3)):
        solid = solid_of({"type": "mesh", "nodes": nodes.tolist(), "hexahedra": [list(range(8))]})
        assert solid.solid.masses.sum() == pytest.approx(RHO * volume, rel=1e-12)
        assert np.allclose(solid.solid.masses, RHO * volume / 8, rtol=1e-12)


def test_h_is_the_lattice_spacing():
    paper = fpm.load_problem(box_spec((10, 10, 10), 0.1 / 9))
    assert paper.h == pytest.approx(0.1 / 9, rel=1e-12)
    assert paper.size == pytest.approx(0.1 * np.sqrt(3), rel=1e-12)
    # Unequal spacing: h is the shortest edge, whatever the connectivity.
    for connectivity in ("axis", "axis+face", "full"):
        p = fpm.load_problem(box_spec((3, 4, 5), (0.02, 0.01, 0.03), connectivity=connectivity))
        assert p.h == pytest.approx(0.01, rel=1e-12)
    # A network: the shortest spring.
    net = fpm.load_problem(
        network_spec(
            [[0, 0, 0], [0.03, 0, 0], [0.03, 0.04, 0]], [(0, 1), (1, 2)], forces={2: [1, 0, 0]}
        )
    )
    assert net.h == pytest.approx(0.03)
    assert net.rest_lengths.tolist() == pytest.approx([0.03, 0.04])


@pytest.mark.parametrize("connectivity", ["axis", "axis+face", "full"])
def test_hexahedron_springs_are_the_unique_sorted_pairs_with_the_lowest_family(connectivity):
    """The springs of a voxel lattice with a hole: every node pair a hexahedron joins, once,
    in lexicographic order, with the lowest family any hexahedron gives it (as np.unique on
    the rows computes it, which the int64 keys replaced)."""
    from fpm.model.geometry import box_hexahedra, hexahedron_springs, local_families, local_pairs

    hexahedra = np.delete(box_hexahedra((5, 4, 4)), 13, axis=0)  # 4 x 3 x 3 cells, one gone
    springs, families = hexahedron_springs(hexahedra, connectivity)
    lp = local_pairs(connectivity)
    pairs = np.stack([hexahedra[:, lp[:, 0]].ravel(), hexahedra[:, lp[:, 1]].ravel()], axis=1)
    pairs.sort(axis=1)
    expected, inverse = np.unique(pairs, axis=0, return_inverse=True)
    lowest = np.full(len(expected), 127, dtype=np.int8)
    np.minimum.at(lowest, inverse.ravel(), np.tile(local_families(connectivity), len(hexahedra)))
    assert springs.dtype == np.int32 and np.array_equal(springs, expected)
    assert np.array_equal(families, lowest)


def test_spacing_is_the_cell_size_where_a_moved_node_shortens_a_spring() -> None:
    """On a regular lattice the stiffness's scale is h; a lattice conformed to a surface moves
    nodes and leaves springs far shorter than its cells: the scale stays the cells' size (the
    median of cube roots of the volumes), and a graded lattice's level-1 cells count double."""
    spacing = np.array([0.01, 0.01, 0.01])
    cells = list(product(range(4), range(4), range(3)))
    regular = solid_of(cells_mesh(cells, spacing, np.random.default_rng(2)))
    assert regular.spacing == pytest.approx(0.01, rel=1e-12)
    assert regular.h == pytest.approx(0.01, rel=1e-12)
    box = fpm.load_problem(box_spec((5, 5, 4)))
    assert box.spacing == box.h  # regular: the shortest spring itself
    moved = cells_mesh(cells, spacing, np.random.default_rng(2))
    corner = int(np.argmin(np.linalg.norm(np.asarray(moved["nodes"]), axis=1)))  # (0, 0, 0)
    moved["nodes"][corner] = [0.008, 0.008, 0.008]  # its body diagonal: 3.5 mm, not 17 mm
    conformed = solid_of(moved)
    assert conformed.h < 0.004
    assert conformed.spacing == pytest.approx(0.01, rel=1e-12)  # 47 of 48 cells unchanged
    spec = box_spec((2, 2, 2), fpm_settings={"stiffness": "families+volume"})
    spec["geometry"] = {**moved, "connectivity": "full"}
    mu = MATERIAL["youngs_modulus"] / (2 * (1 + MATERIAL["poisson_ratio"]))
    k1 = continuum_start(fpm.load_problem(spec))[0]
    assert k1 == pytest.approx(mu * 0.01, rel=1e-12)  # k1 = mu h, h the cells' size
    graded = solid_of({**cells_mesh(cells, spacing / 2, np.random.default_rng(2)),
                       "levels": [1] * len(cells)})  # fmt: skip
    assert graded.spacing == pytest.approx(0.01, rel=1e-12)
