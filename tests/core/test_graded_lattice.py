"""The graded lattice: parts one cell thick refined 2x2x2 from the mesh (fpm.io.meshes.graded),
their interfaces inside the solid, each cell's springs at its own size, and the budget kept."""

from __future__ import annotations

import itertools

import meshio
import numpy as np
import pytest

import fpm
from fpm.io.meshes import spec_from_mesh
from fpm.io.meshes.graded import graded_lattice, run_lengths, thin_groups
from fpm.model.geometry import boundary_faces, lumped_masses, thin_parts
from fpm.model.hexahedron import NATURAL
from fpm.model.shares import cell_shares
from tests.core.test_meshes import kuhn_box

MATERIAL = {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040.0}


def cells_lattice(cells: list[tuple[tuple[int, int, int], int]]) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) and hexahedra (H, 8) of axis-aligned cubes, each (origin, size) on the
    integer grid, nodes joined where they coincide."""
    index: dict[tuple[int, ...], int] = {}
    hexahedra = []
    for origin, size in cells:
        corners = np.asarray(origin) + (NATURAL > 0) * size
        hexahedra.append([index.setdefault(tuple(c), len(index)) for c in corners.tolist()])
    nodes = np.array(sorted(index, key=index.__getitem__), dtype=float)
    return nodes, np.asarray(hexahedra)


def coarse_and_fine() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A cube of size 2 at the origin beside the same cube split into 8 of size 1 (along +x),
    and their levels."""
    cells = [((0, 0, 0), 2)] + [
        ((2 + i, j, k), 1) for i, j, k in itertools.product((0, 1), repeat=3)
    ]
    nodes, hexahedra = cells_lattice(cells)
    return nodes, hexahedra, np.array([0] + [1] * 8)


def test_a_coarse_face_covered_by_four_fine_faces_is_inside_the_solid():
    nodes, hexahedra, _ = coarse_and_fine()
    free = boundary_faces(hexahedra)
    assert not free[0, 1]  # the coarse cube's x+ face
    assert free[0].sum() == 5
    # the fine block's outer faces: 6 sides x 4 quarters, less the 4 against the coarse cube
    assert free[1:].sum() == 20
    # a lattice of one size has no such interface: every unmatched face is surface
    nodes, hexahedra = cells_lattice([(c, 1) for c in itertools.product(range(3), repeat=3)])
    assert boundary_faces(hexahedra).sum() == 6 * 9


def test_a_graded_lattice_stores_the_energy_of_a_uniform_strain_as_one_of_one_size():
    """k ~ mu h: a cell of half the size gives its springs half of its family's k, so under an
    affine displacement the springs store the same energy per volume in every cell, and the
    graded block stores what the same block of one cell size does (the springs' patch energy);
    the lumped masses are the solid's."""
    graded = coarse_and_fine()
    uniform = cells_lattice([((0, 0, 0), 2), ((2, 0, 0), 2)]) + (np.zeros(2, int),)
    strain = np.array([[1e-3, 2e-4, 0.0], [2e-4, -5e-4, 3e-4], [0.0, 3e-4, 8e-4]])
    energies = []
    for nodes, hexahedra, levels in (graded, uniform):
        spec = {
            "name": "block",
            "material": MATERIAL,
            "geometry": {
                "type": "mesh",
                "nodes": (nodes * 0.01).tolist(),
                "hexahedra": hexahedra.tolist(),
                "levels": levels.tolist(),
            },
            "fixed": [{"face": "x-"}],
            "load_cases": [{"name": "pull", "forces": [{"face": "x+", "vector": [0.01, 0, 0]}]}],
            "fpm": {"stiffness": "families+volume"},
        }
        problem = fpm.load_problem(spec)
        k = np.asarray(cell_shares(problem).sum(axis=1)).ravel()  # every family at k = 1
        x = problem.nodes
        u = x @ strain.T
        springs = problem.solid.springs
        d0 = x[springs[:, 1]] - x[springs[:, 0]]
        du = u[springs[:, 1]] - u[springs[:, 0]]
        stretch = np.einsum("ij,ij->i", d0, du) / np.linalg.norm(d0, axis=1)  # first order
        energies.append(0.5 * np.sum(k * stretch**2))
        volume = 2 * 0.02**3
        assert lumped_masses(x, hexahedra, 1040.0).sum() == pytest.approx(1040.0 * volume)
    assert energies[0] == pytest.approx(energies[1], rel=1e-12)


def test_runs_and_thin_groups_of_an_occupancy():
    occ = np.zeros((6, 6, 4), dtype=bool)
    occ[:, :, 0] = True  # a sheet one cell thick
    occ[:2, :2, :] = True  # a post four cells tall
    runs = run_lengths(occ)
    assert runs[2, 5, 5, 0] == 1 and runs[2, 0, 0, 0] == 4 and runs[0, 3, 3, 0] == 6
    groups = thin_groups(occ)
    assert len(groups) == 1 and len(groups[0]) == 36 - 4  # the sheet less under the post


def plate(thickness: float, side: float = 0.06) -> meshio.Mesh:
    """A square plate of the given thickness (m), tetrahedralised."""
    points, tets, _ = kuhn_box([0, 0, 0], [side, side, thickness], 4)
    return meshio.Mesh(points, [("tetra", tets)])


def test_a_plate_one_cell_thick_is_refined_to_two_from_the_mesh():
    """An 8 mm plate at h = 10 mm is one cell thick: voxelised again at 5 mm it is two cells
    thick, every cell of level 1; the part is named with its place and the nodes it took."""
    from fpm.io.meshes.voxelise import voxelise_tetrahedra

    mesh = plate(0.008)
    points, tets = mesh.points, mesh.cells[0].data
    occ, origin = voxelise_tetrahedra(points, tets, 0.01)
    assert occ.shape[2] == 1 and occ.all()
    lattice = graded_lattice(occ, origin, 0.01, points, tets)
    assert lattice.refined and set(lattice.levels.tolist()) == {1}
    assert len(lattice.hexahedra) == 12 * 12 * 2
    assert len(lattice.nodes) == 13 * 13 * 3
    (part,) = lattice.parts
    assert part.thin_cells == 36 and part.cells == 36 and part.still_thin == 0
    assert part.nodes_added == 13 * 13 * 3 - 7 * 7 * 2
    np.testing.assert_allclose(part.centre, [0.03, 0.03, 0.004])  # the lattice is centred
    assert thin_parts(lattice.hexahedra) == []


def test_a_wall_thinner_than_h_half_between_the_cell_centres_is_kept():
    """A 3 mm plate lying between z = 3 and 6 mm, on a lattice of h = 10 mm from z = 0, holds
    none of its cells' octant centres (z = 2.5, 7.5 mm), nor of the h/2 cells' centres: its
    tetrahedra's centroids keep it, in the voxels and through the refinement (the hollow
    organ's flat caps fell between them, and its wall was open at both ends)."""
    from fpm.io.meshes.geometry import octant_occupancy

    points, tets, _ = kuhn_box([0, 0, 0.003], [0.06, 0.06, 0.006], 4)
    cells = np.array([6, 6, 1])
    occ = octant_occupancy(points, tets, 0.01, np.zeros(3), cells)
    assert occ.all()
    lattice = graded_lattice(occ, np.zeros(3), 0.01, points, tets)
    assert lattice.refined and set(lattice.levels.tolist()) == {1}
    assert len(lattice.hexahedra) == 12 * 12 * 2  # the cells of h/2 it crosses, all kept


def test_the_hollow_organ_is_closed_at_both_caps_and_pressed_where_asked():
    """The generated hollow organ (a 5.6-8 mm wall) at about 2,000 nodes: every point of the
    mesh lies within a spacing of a lattice node (its flat caps were lost, a hole of 5 cm
    across at the top and the bottom), and the press at the top's centre finds a node there."""
    from scipy.spatial import cKDTree

    from bench.anatomy import ORGANS

    organ = ORGANS["hollow"]
    mesh = organ.mesh()
    spec, notes = spec_from_mesh(mesh, nodes=2000, **organ.presses(mesh), **MATERIAL)
    problem = fpm.load_problem(spec)
    h = float(min(spec["geometry"].get("spacing", [0.0]) or [0.0])) or next(
        float(n.split("h = ")[1].split(" m")[0]) for n in notes if n.startswith("voxelised")
    )
    gap, _ = cKDTree(problem.nodes).query(np.asarray(mesh.points))
    assert gap.max() < h, notes[1]
    press = [n for n in notes if n.startswith("load_cases.0.forces.0.nearest")]
    assert not press or float(press[0].split(" is ")[1].split(" mm")[0]) < 1e3 * h / 2


def wedge(n: int = 10) -> meshio.Mesh:
    """A lobe 0.2 x 0.1 m tapering from 40 mm thick to 1 mm along x."""
    points, tets, _ = kuhn_box([0, 0, -0.5], [1, 1, 0.5], n)
    thickness = 0.04 + (0.001 - 0.04) * points[:, 0]
    out = np.stack([0.2 * points[:, 0], 0.1 * points[:, 1], points[:, 2] * thickness], axis=1)
    return meshio.Mesh(out, [("tetra", tets)])


def test_a_tapering_lobe_is_modelled_not_refused_within_the_node_budget():
    """The rim of a lobe is one cell thick at every spacing: spec_from_mesh refines it (a
    graded lattice, named in the notes with its place and nodes) and keeps --nodes within 30%
    of the count asked, refinement included; the problem loads (what is still one cell thick
    at h/2 is a warning, not a refusal)."""
    given = dict(
        fix=["face:x-"],
        forces=["nearest:0.15,0.05,0.01:0,0,-0.01"],
        **MATERIAL,
    )
    spec, notes = spec_from_mesh(wedge(), spacing=0.008, **given)
    refined = [n for n in notes if n.startswith("graded lattice: part")]
    assert refined and "refined to h/2" in refined[0] and "nodes" in refined[0]
    levels = np.asarray(spec["geometry"]["levels"])
    assert set(levels.tolist()) == {0, 1}
    problem = fpm.load_problem(spec)
    assert problem.solid.levels is not None
    free = boundary_faces(problem.solid.elements())
    assert free.any(axis=1).sum() < len(levels)  # interior cells remain
    for asked in (600, 2000):
        spec, notes = spec_from_mesh(wedge(), nodes=asked, **given)
        assert abs(fpm.load_problem(spec).n_nodes / asked - 1) <= 0.3, notes[0]


def test_the_json_export_alone_rebuilds_a_graded_lattice():
    """The export carries the graded lattice as it is (springs at their cells' sizes, every
    cell's volume term, the masses): an independent linear solve of the JSON alone equals the
    project's static equilibrium on the refined plate at a small load; a fine cell's interior
    edge has half the k of a coarse one's."""
    import json

    from fpm.dynamics.equilibrium import static_equilibrium
    from fpm.io.export import export
    from tests.core.test_export import independent_linear_solve

    thick = meshio.Mesh(*_plate_on_block())
    spec, notes = spec_from_mesh(
        thick,
        spacing=0.006,
        fix=["face:z-"],
        forces=["nearest:0.05,0.02,0.012:0,0,-1e-8", "nearest:0.02,0.02,0.018:1e-8,0,0"],
        stiffness="families+volume",
        **MATERIAL,
    )
    assert any(n.startswith("graded lattice: part") for n in notes)
    problem = fpm.load_problem(spec)
    levels = problem.solid.levels
    assert levels is not None and 0 < levels.sum() < len(levels)
    theta = [30.0, 20.0, 4.0, 2e4]
    record = {"stiffness": {"axis": 30.0, "face": 20.0, "body": 4.0}, "volume_stiffness": 2e4,
              "d": 0.05, "depth": None, "dt": 1e-4}  # fmt: skip
    model = json.loads(export(problem, record, "json"))
    assert len(model["hexahedra"]) == len(levels)
    k = np.asarray(cell_shares(problem).sum(axis=1)).ravel()
    assert k.max() == pytest.approx(1.0) and k[k > 0].min() < 0.25  # fine surface edges: 1/8
    for j in range(2):
        ours = static_equilibrium(problem, k=theta, load_case=j, tolerance=1e-10).displacements
        theirs = independent_linear_solve(model, j)
        assert np.abs(ours - theirs).max() < 1e-5 * np.abs(ours).max()


def _plate_on_block() -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """A 3.6 x 3.6 x 1.8 cm block with a 6 mm flap standing out 2.4 cm on one side."""
    from tests.core.test_fuzz_meshes import grid_tetrahedra

    keep = np.zeros((10, 6, 6), dtype=bool)
    keep[:6] = True  # the block, x < 0.036
    keep[6:, :, 2:4] = True  # the flap: two layers of the grid, 6 mm thick, beyond it
    points, tets = grid_tetrahedra((10, 6, 6), np.array([0.06, 0.036, 0.018]), keep)
    return points, [("tetra", tets)]


def test_a_part_refined_in_one_region_with_an_earlier_one_is_named_and_counted_once():
    """Two thin parts whose refined neighbourhoods join are one region of h/2: the notes count
    its cells and nodes once, under the first, and say the second was refined with it."""
    from types import SimpleNamespace

    from fpm.io.meshes.conform import refined_notes
    from fpm.io.meshes.graded import RefinedPart

    first = RefinedPart(np.array([0.0, 0.0, 0.0]), thin_cells=27, cells=102, nodes_added=1168)
    second = RefinedPart(np.array([0.1, 0.0, 0.0]), thin_cells=10, cells=0, with_part=0)
    notes = refined_notes(SimpleNamespace(parts=[first, second], spacing=0.0157))
    assert "refined to h/2 over 102 cells: 1168 nodes" in notes[0]
    assert "part 2 one cell thick" in notes[1] and "with part 1 (one region" in notes[1]
    assert "over 0 cells" not in notes[1]
