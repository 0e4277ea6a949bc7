"""Mesh import (fpm/io/meshes/): hexahedral meshes as they are, tetrahedra and closed surfaces
voxelised with exact inside tests, open surfaces refused, and `fpmcal spec from-mesh`."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import meshio
import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

import fpm
from client import spec_from_mesh as sdk_spec_from_mesh
from fpm.io.meshes import (
    MeshError,
    geometry_from_mesh,
    lattice,
    parse_force,
    parse_selector,
    read_mesh,
    spec_from_mesh,
    voxelise_surface,
    voxelise_tetrahedra,
)
from fpm.model.geometry import voxel_mesh
from fpm.model.spec import VoxelGeometry
from fpm.model.tetrahedra import face_pieces
from fpmcal.cli import main

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())
MATERIAL = {"youngs_modulus": 1e4, "poisson_ratio": 0.45, "density": 1040.0}


def small_box_mesh() -> meshio.Mesh:
    """examples/small-box.json's hexahedra as a meshio mesh (VTK node order)."""
    problem = fpm.load_problem(SMALL)
    return meshio.Mesh(problem.nodes, [("hexahedron", problem.solid.elements())])


def kuhn_box(lo: Any, hi: Any, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, tetrahedra (6 per cell, Kuhn) and boundary triangles of a box of n^3 cells."""
    axes = [np.linspace(lo[a], hi[a], n + 1) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    index = np.arange(len(grid)).reshape(n + 1, n + 1, n + 1)

    def corner(i: int, j: int, k: int) -> np.ndarray:
        return index[i : n + i, j : n + j, k : n + k].ravel()

    c = [corner(*o) for o in [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
                              (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]]  # fmt: skip
    kuhn = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]
    tets = np.concatenate([np.stack([c[a], c[b], c[e], c[f]], axis=1) for a, b, e, f in kuhn])
    faces = np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    return grid, tets, unique[count == 1]


def ball(r: float, surface: int, interior: int, seed: int = 0) -> np.ndarray:
    """Points on a sphere of radius r and inside it (a Delaunay mesh of them fills their
    convex hull: a polyhedron inscribed in the sphere)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(surface, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    inner = rng.uniform(-1, 1, size=(interior, 3))
    inner = inner[np.linalg.norm(inner, axis=1) < 0.97]
    return np.vstack([u, inner]) * r


def centres(points: np.ndarray, h: float) -> np.ndarray:
    """(cx, cy, cz, 3) cell centres of the lattice the voxelisers build for ``points``."""
    origin, cells = lattice(points.min(axis=0), points.max(axis=0), h)
    axes = [origin[a] + h * (np.arange(cells[a]) + 0.5) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


# ------------------------------------------------------------------ hexahedral meshes


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".inp", ".vtk"])
def test_a_hexahedral_mesh_round_trips_to_the_same_lattice_and_fem(tmp_path: Path, suffix: str):
    path = tmp_path / f"box{suffix}"
    meshio.write(path, small_box_mesh())
    spec, _ = spec_from_mesh(
        path, fix=["face:z-"], forces=["at:0.01,0.01,0.03:0,0,0.05"], **MATERIAL, dt=1e-3
    )
    assert spec["geometry"]["type"] == "mesh"
    built = fpm.load_problem(SMALL)
    read = fpm.load_problem(spec)
    np.testing.assert_allclose(read.nodes, built.nodes, atol=1e-12)
    np.testing.assert_array_equal(read.solid.elements(), built.solid.elements())
    np.testing.assert_array_equal(read.solid.springs, np.unique(built.solid.springs, axis=0))
    np.testing.assert_allclose(read.solid.masses, built.solid.masses, rtol=1e-12)
    np.testing.assert_array_equal(read.fixed, built.fixed)
    fem_read = fpm.solve_fem(read).displacements
    fem_built = fpm.solve_fem(built).displacements[:1]
    np.testing.assert_allclose(fem_read, fem_built, rtol=1e-9, atol=1e-15)


def test_an_inside_out_hexahedron_is_renumbered_and_unused_nodes_dropped():
    mesh = small_box_mesh()
    hexes = mesh.cells[0].data.copy()
    hexes[0] = hexes[0][[4, 5, 6, 7, 0, 1, 2, 3]]  # upside down: negative volume
    points = np.vstack([mesh.points, [[9.0, 9.0, 9.0]]])  # a node in no hexahedron
    made = geometry_from_mesh(meshio.Mesh(points, [("hexahedron", hexes)]))
    assert len(made.geometry["nodes"]) == len(mesh.points)
    assert any("renumbered" in n for n in made.notes) and any("dropped" in n for n in made.notes)
    from fpm.model.geometry import hexahedron_volumes

    volumes = hexahedron_volumes(
        np.asarray(made.geometry["nodes"]), np.asarray(made.geometry["hexahedra"])
    )
    assert (volumes > 0).all()


# ------------------------------------------------------------------ voxelising


@pytest.mark.parametrize("rotated", [False, True], ids=["aligned", "rotated"])
@pytest.mark.parametrize(
    ("hi", "n", "h"),
    [((0.95, 0.95, 0.95), 18, 0.1), ((1.0, 0.7, 0.45), 7, 0.1), ((0.9, 0.5, 0.3), 5, 0.07)],
    ids=["vertices-on-rays", "odd-box", "coarse"],
)
def test_a_tetrahedralised_box_voxelises_to_the_analytic_cells(rotated: bool, hi, n, h):
    """Tetrahedra and the boundary triangles of the same box give exactly the cells whose centre
    the box holds, also when rays run through the triangulation's vertices and edges (the
    first case: a vertex every h/2, cell centres on them)."""
    lo = np.array([0.05, 0.05, 0.05])
    points, tets, triangles = kuhn_box(lo, np.asarray(hi), n)
    rotation = np.eye(3)
    if rotated:
        rotation = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    moved = points @ rotation.T
    in_box = centres(moved, h) @ rotation  # back in the box's frame
    analytic = np.all((in_box > lo) & (in_box < np.asarray(hi)), axis=-1)
    from_tets, _ = voxelise_tetrahedra(moved, tets, h)
    from_surface, _ = voxelise_surface(moved, triangles, h)
    assert analytic.any()
    np.testing.assert_array_equal(from_tets, analytic)
    np.testing.assert_array_equal(from_surface, analytic)


def test_a_sphere_from_tetrahedra_and_from_its_surface():
    """h = r/10: the same cells from the tetrahedra and from their boundary (both exact tests of
    one polyhedron), the analytic sphere's cells wherever the polyhedron and the sphere agree,
    and a volume within 3% of 4/3 pi r^3."""
    r = 0.05
    h = r / 10
    points = ball(r, 1500, 4000)
    tets = Delaunay(points).simplices
    hull = ConvexHull(points).simplices
    from_tets, _ = voxelise_tetrahedra(points, tets, h)
    from_surface, _ = voxelise_surface(points, hull, h)
    np.testing.assert_array_equal(from_tets, from_surface)

    distance = np.linalg.norm(centres(points, h), axis=-1)
    analytic = distance < r
    # The inscribed polyhedron lies between the sphere and a sphere a little inside it.
    normals = np.cross(
        points[hull[:, 1]] - points[hull[:, 0]], points[hull[:, 2]] - points[hull[:, 0]]
    )
    inradius = np.min(np.abs(np.einsum("ij,ij->i", normals, points[hull[:, 0]]))
                      / np.linalg.norm(normals, axis=1))  # fmt: skip
    sure = (distance < inradius) | (distance > r)
    np.testing.assert_array_equal(from_tets[sure], analytic[sure])
    assert (~sure).sum() < 0.1 * analytic.sum()

    exact = 4 / 3 * np.pi * r**3
    for occupancy in (from_tets, from_surface):
        assert abs(occupancy.sum() * h**3 / exact - 1) < 0.03


def test_an_open_surface_is_refused_with_a_clear_message(tmp_path: Path):
    points = ball(0.05, 400, 0)
    hull = ConvexHull(points).simplices
    path = tmp_path / "cup.stl"
    meshio.write(path, meshio.Mesh(points, [("triangle", hull[1:])]), binary=True)  # one missing
    with pytest.raises(MeshError, match=r"the surface is not closed: 3 of its edges belong to"):
        spec_from_mesh(path, spacing=0.005, fix=["face:z-"], forces=["face:z+:0,0,-1"], **MATERIAL)
    assert main(["spec", "from-mesh", str(path), "--spacing", "0.005", "--fix", "face:z-",
                 "--force", "face:z+:0,0,-1", "--E", "5000", "--nu", "0.45"]) == 2  # fmt: skip


def test_a_closed_stl_surface_voxelises(tmp_path: Path):
    """An STL repeats every vertex per triangle: the points are merged before the parity test."""
    r = 0.04
    points = ball(r, 600, 0, seed=2)
    hull = ConvexHull(points).simplices
    path = tmp_path / "ball.stl"
    soup = [("triangle", np.arange(3 * len(hull)).reshape(-1, 3))]
    meshio.write(path, meshio.Mesh(points[hull].reshape(-1, 3), soup), binary=True)
    made = geometry_from_mesh(read_mesh(path), spacing=r / 8)
    assert made.kind == "surface"
    cells = np.asarray(made.geometry["occupancy"]).sum()
    assert abs(cells * (r / 8) ** 3 / (4 / 3 * np.pi * r**3) - 1) < 0.06


def test_fifty_thousand_tetrahedra_to_twenty_thousand_nodes_under_ten_seconds():
    r = 0.05
    points = ball(r, 3000, 14000)
    tets = Delaunay(points).simplices
    assert len(tets) >= 50_000
    t0 = time.perf_counter()
    made = geometry_from_mesh(meshio.Mesh(points, [("tetra", tets)]), spacing=r / 17)
    seconds = time.perf_counter() - t0
    nodes, _ = voxel_mesh(VoxelGeometry(**made.geometry))
    assert 17_000 < len(nodes) < 24_000
    assert seconds < 10, seconds


def test_mesh_errors_say_what_to_do(tmp_path: Path):
    tets = meshio.Mesh(ball(0.05, 100, 100), [("tetra", Delaunay(ball(0.05, 100, 100)).simplices)])
    with pytest.raises(MeshError, match=r"give its spacing h > 0 in m .* \(--nodes\)"):
        geometry_from_mesh(tets)
    sliver = meshio.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.01]]),
                         [("tetra", np.array([[0, 1, 2, 3]]))])  # fmt: skip
    with pytest.raises(MeshError, match="no cell centre lies inside the solid"):
        geometry_from_mesh(sliver, spacing=10.0)
    lines = meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))])
    with pytest.raises(MeshError, match="no volume cells and no surface triangles"):
        geometry_from_mesh(lines, spacing=0.1)
    (tmp_path / "broken.vtu").write_text("<VTKFile>")
    with pytest.raises(MeshError, match="cannot read it as a mesh"):
        read_mesh(tmp_path / "broken.vtu")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(MeshError, match="not a mesh format"):
        read_mesh(tmp_path / "notes.txt")


# ------------------------------------------------------------------ selectors and the command


def test_selectors_and_forces_in_short_form():
    assert parse_selector("face:z-") == {"face": "z-"}
    assert parse_selector("node:12") == {"node": 12}
    assert parse_selector("nearest:0,0,0.05") == {"nearest": [0.0, 0.0, 0.05]}
    assert parse_selector("box:0,0,0:1,1,0.01") == {"box": [[0, 0, 0], [1, 1, 0.01]]}
    assert parse_force("face:z+:0,0,-2:distribute") == [
        {"face": "z+", "vector": [0, 0, -2], "distribute": True}
    ]
    assert parse_force("at:0,0,1e-2:1,0,0; node:3:0,0,-1") == [
        {"at": [0, 0, 0.01], "vector": [1, 0, 0]},
        {"node": 3, "vector": [0, 0, -1]},
    ]
    for bad, reason in [
        ("face:z", "a face is one of"),
        ("sphere:0,0,0", "a selector is"),
        ("nearest:0,0", "three numbers"),
        ("box:0,0,0", "two corners"),
    ]:
        with pytest.raises(ValueError, match=reason):
            parse_selector(bad)
    with pytest.raises(ValueError, match="give the force after the selector"):
        parse_force("face:z+")
    with pytest.raises(ValueError, match="only ':distribute' may follow"):
        parse_force("face:z+:0,0,1:spread")


def test_spec_from_mesh_command_line_and_sdk_agree(tmp_path: Path, capsys):
    points = ball(0.03, 300, 600)
    path = tmp_path / "lobe.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", Delaunay(points).simplices)]))
    out = tmp_path / "lobe.json"
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.006", "--fix", "box:-1,-1,-1:1,1,-0.02",
            "--force", "nearest:0,0,0.03:0,0,-0.01", "--force", "face:z+:0.01,0,0:distribute",
            "--validate", "nearest:0.01,0,0.02:0,0.01,0",
            "--E", "5000", "--nu", "0.45", "--density", "1040", "-o", str(out)]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "voxelised" in err and "fpm.dt =" in err and "nearest: node" in err
    spec = json.loads(out.read_text())
    problem = fpm.load_problem(spec)
    # the default lattice follows the mesh's surface (a hexahedral mesh geometry)
    assert spec["geometry"]["type"] == "mesh" and problem.fixed.any()
    assert [c.name for c in problem.load_cases] == [
        "nearest:0,0,0.03:0,0,-0.01",
        "face:z+:0.01,0,0:distribute",
    ]
    np.testing.assert_allclose(problem.load_cases[1].forces.sum(axis=0), [0.01, 0, 0])
    # a validation case, never fitted, in the forces' form
    assert [c.name for c in problem.validation_cases] == ["nearest:0.01,0,0.02:0,0.01,0"]
    np.testing.assert_allclose(problem.validation_cases[0].forces.sum(axis=0), [0, 0.01, 0])
    assert spec["fpm"]["dt"] == "auto"
    sdk = sdk_spec_from_mesh(
        path,
        spacing=0.006,
        fix=["box:-1,-1,-1:1,1,-0.02"],
        forces=["nearest:0,0,0.03:0,0,-0.01", "face:z+:0.01,0,0:distribute"],
        youngs_modulus=5000,
        poisson_ratio=0.45,
        density=1040,
        validation=["nearest:0.01,0,0.02:0,0.01,0"],
    )
    assert sdk == spec
    # a bad validation force is one line naming it, as a bad --force is
    argv[argv.index("--validate") + 1] = "nearest:0.01,0,0.02:0,0.01"
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "0,0.01" in err


def test_a_mesh_given_as_spec_points_at_from_mesh(tmp_path: Path, capsys):
    meshio.write(tmp_path / "lobe.vtu", small_box_mesh())
    assert main(["calibrate", str(tmp_path / "lobe.vtu")]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert err.startswith(
        f"SPEC must be a JSON problem spec (got {tmp_path / 'lobe.vtu'}, not JSON"
    )
    assert "looks like a mesh: make a spec of it first with fpmcal spec from-mesh" in err


def test_a_bad_selector_is_one_line(tmp_path: Path, capsys):
    meshio.write(tmp_path / "box.vtu", small_box_mesh())
    argv = ["spec", "from-mesh", str(tmp_path / "box.vtu"), "--fix", "face:q",
            "--force", "face:z+:0,0,1", "--E", "1e4", "--nu", "0.3"]  # fmt: skip
    assert main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [
        "error: 'face:q': a face is one of x-, x+, y-, y+, z-, z+ (e.g. face:z-)"
    ]


# --- meshes users actually have: Gmsh v1, VTK POLYDATA, fragments -----------------------------


def write_gmsh1(path: Path, points: np.ndarray, tets: np.ndarray) -> None:
    """A Gmsh legacy v1 file (ids from 10, in reverse order: the reader maps ids, not rows)."""
    ids = 10 + np.arange(len(points))[::-1]
    lines = ["$NOD", str(len(points))]
    lines += [f"{i} {x!r} {y!r} {z!r}" for i, (x, y, z) in zip(ids, points.tolist(), strict=True)]
    lines += ["$ENDNOD", "$ELM", str(len(tets) + 1), "1 15 0 0 1 " + str(ids[0])]  # a point
    lines += [f"{e + 2} 4 1 1 4 " + " ".join(str(ids[n]) for n in t) for e, t in enumerate(tets)]
    lines += ["$ENDELM", ""]
    path.write_text("\n".join(lines))


def write_polydata(path: Path, points: np.ndarray, triangles: np.ndarray) -> None:
    lines = ["# vtk DataFile Version 3.0", "surface", "ASCII", "DATASET POLYDATA",
             f"POINTS {len(points)} double"]  # fmt: skip
    lines += [" ".join(repr(v) for v in p) for p in points.tolist()]
    lines += [f"POLYGONS {len(triangles)} {4 * len(triangles)}"]
    lines += ["3 " + " ".join(map(str, t)) for t in triangles.tolist()]
    path.write_text("\n".join(lines) + "\n")


def test_gmsh_v1_and_vtk_polydata_import_as_their_modern_forms_do(tmp_path: Path):
    """The same tetrahedralised box as Gmsh v1 (which meshio cannot read) and as Gmsh 2.2, and
    its boundary as a VTK POLYDATA surface: the same lattice from all three."""
    points, tets, triangles = kuhn_box([0, 0, 0], [0.04, 0.03, 0.02], 4)
    write_gmsh1(tmp_path / "old.msh", points, tets)
    meshio.write(tmp_path / "new.msh", meshio.Mesh(points, [("tetra", tets)]),
                 file_format="gmsh22")  # fmt: skip
    write_polydata(tmp_path / "surface.vtk", points, triangles)
    made = [geometry_from_mesh(read_mesh(tmp_path / f), spacing=0.005).geometry
            for f in ("old.msh", "new.msh", "surface.vtk")]  # fmt: skip
    assert made[0] == made[1] == made[2]
    assert np.asarray(made[0]["occupancy"]).sum() == 8 * 6 * 4


@pytest.mark.parametrize(
    ("name", "text", "reason"),
    [
        ("cut.msh", "$NOD\n2\n1 0 0 0\n", "not a readable Gmsh v1 file"),
        ("bad.vtk", "# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\n",
         "binary VTK is not read"),
        ("open.vtk", "# vtk DataFile Version 3.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n"
         "0 0 0 1 0 0 0 1 0\nPOLYGONS 1 4\n3 0 1 7\n", "names a point that does not exist"),
    ],
)  # fmt: skip
def test_a_broken_legacy_file_is_one_line_in_the_cli(tmp_path: Path, capsys, name, text, reason):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(MeshError, match=reason):
        read_mesh(path)
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.01", "--fix", "face:z-",
            "--force", "face:z+:0,0,1", "--E", "5000", "--nu", "0.45"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and reason in err[0]


def test_cells_joined_by_less_than_a_face_are_dropped_and_the_fem_holds_the_rest(tmp_path: Path):
    """A block with a cube touching it only along an edge (and one only at a corner): both are
    dropped with a note of how many cells and how much volume, and the FEM accepts the spec."""
    h = 0.01
    block = kuhn_box([0, 0, 0], [0.04, 0.04, 0.03], 4)
    edge = kuhn_box([0.04, 0.04, 0.0], [0.05, 0.05, 0.01], 1)  # shares the edge x=y=0.04
    corner = kuhn_box([0.04, 0.04, 0.03], [0.05, 0.05, 0.04], 1)  # shares the corner only
    points, tets = block[0], block[1]
    for p, t, _ in (edge, corner):
        tets = np.concatenate([tets, t + len(points)])
        points = np.concatenate([points, p])
    path = tmp_path / "fragments.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", tets)]))
    spec, notes = spec_from_mesh(
        path, fix=["face:z-"], forces=["face:z+:0,0,0.01:distribute"], youngs_modulus=5e3,
        poisson_ratio=0.45, spacing=h, lattice="voxels",
    )  # fmt: skip
    assert np.asarray(spec["geometry"]["occupancy"]).sum() == 4 * 4 * 3
    dropped = [n for n in notes if n.startswith("dropped")]
    assert dropped and "dropped 2 cells (2e-06 m^3" in dropped[0]
    # The reference mesh is the same solid: the two cubes' 12 tetrahedra are left out with it
    # (the corner cube, joined by nothing, would float, and a load spread over the lattice's
    # top corner's patch reached it: the refined reference raised "can still move freely").
    assert len(spec["reference"]["mesh"]["tetrahedra"]) == len(tets) - 12
    left_out = [n for n in notes if n.startswith("reference.mesh: left out")]
    assert left_out and "left out 12 tetrahedra (2e-06 m^3) in 2 piece(s)" in left_out[0]
    for refine in (0, 1):  # as given with point loads; one refinement with the loads spread
        spec["reference"]["refine"] = refine
        fem = fpm.solve_fem(fpm.load_problem(spec))  # held: no "can still move freely"
        assert np.all(np.isfinite(fem.displacements)) and fem.refinements == refine


def test_face_pieces_join_tetrahedra_through_faces_at_the_same_positions():
    """Two cubes sharing a face are one piece, whether the mesh numbers the face's corners once
    or twice (coincident nodes); a cube touching them along an edge only is a piece of its own,
    and so is one touching at a corner."""
    a = kuhn_box([0, 0, 0], [1, 1, 1], 1)
    b = kuhn_box([1, 0, 0], [2, 1, 1], 1)  # shares the face x = 1, its own copies of its nodes
    edge = kuhn_box([2, 1, 0], [3, 2, 1], 1)  # the edge x = 2, y = 1
    corner = kuhn_box([3, 2, 1], [4, 3, 2], 1)  # the corner (3, 2, 1)
    points, tets = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    for p, t, _ in (a, b, edge, corner):
        tets = np.concatenate([tets, t + len(points)])
        points = np.concatenate([points, p])
    pieces = face_pieces(points, tets)
    assert [len(set(pieces[6 * i : 6 * i + 6])) for i in range(4)] == [1, 1, 1, 1]
    assert pieces[0] == pieces[6] and len({pieces[0], pieces[12], pieces[18]}) == 3
    # numbered once (the shared corners merged), the same pieces
    merged, inverse = np.unique(points, axis=0, return_inverse=True)
    np.testing.assert_array_equal(face_pieces(merged, inverse.reshape(-1)[tets]), pieces)


def test_the_conforming_lattice_lies_on_the_mesh_surface_and_calibrates(tmp_path: Path):
    """spec_from_mesh(conform=True) on the organ of bench/tet_organ.py: the voxels' hexahedra
    with their surface nodes moved onto the mesh's surface (mean distance under a quarter of
    the voxels'), every hexahedron keeping at least KEPT_JACOBIAN of its voxel's smallest
    Jacobian, the fixed face held at the same nodes (now a box), and a calibration runs."""
    from bench.tet_organ import organ_mesh
    from fpm.fem.elasticity import min_jacobian_determinants
    from fpm.fem.samples import lattice_surface
    from fpm.io.meshes import KEPT_JACOBIAN
    from fpm.model.tetrahedra import TetMesh

    nodes, tets = organ_mesh((4, 3, 4))
    mesh = meshio.Mesh(nodes, [("tetra", tets)])
    given = dict(
        fix=["face:z-"], forces=["nearest:0,0,0.035:0,0,-0.01", "nearest:0.07,0,0:0.005,0,0"],
        youngs_modulus=5e3, poisson_ratio=0.45, spacing=0.01,
    )  # fmt: skip
    voxels, _ = spec_from_mesh(mesh, lattice="voxels", **given)
    spec, notes = spec_from_mesh(mesh, **given)  # the default lattice
    assert spec == spec_from_mesh(mesh, conform=True, **given)[0]
    assert spec["geometry"]["type"] == "mesh" and "box" in spec["fixed"][0]
    assert any("surface nodes moved onto the mesh's surface" in n for n in notes)
    before, after = fpm.load_problem(voxels), fpm.load_problem(spec)
    hexahedra = after.solid.elements()
    np.testing.assert_array_equal(before.solid.elements(), hexahedra)
    np.testing.assert_array_equal(before.fixed, after.fixed)
    surface = lattice_surface(hexahedra, after.n_nodes)
    gap = [
        TetMesh(nodes, tets).nearest_on_boundary(p.nodes[surface])[2].mean()
        for p in (before, after)
    ]
    assert gap[1] < 0.25 * gap[0], gap
    kept = min_jacobian_determinants(after.nodes[hexahedra])
    assert np.all(kept >= KEPT_JACOBIAN * min_jacobian_determinants(before.nodes[hexahedra]))
    with pytest.raises(MeshError, match="tetrahedral mesh"):
        spec_from_mesh(mesh, conform=True, voxel_reference=True, **given)
    path, out = tmp_path / "organ.vtu", tmp_path / "organ.json"
    meshio.write(path, mesh)
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.01", "--fix", "face:z-",
            "--E", "5000", "--nu", "0.45", "-o", str(out)]  # fmt: skip
    for force in given["forces"]:
        argv += ["--force", force]
    assert main(argv) == 0
    assert json.loads(out.read_text())["geometry"] == spec["geometry"]
    spec["reference"]["refine"] = 0  # the mesh as given: quick
    problem = fpm.load_problem(spec)
    result = fpm.calibrate(problem, reference=fpm.solve_fem(problem))
    assert (
        result.parameters.volume_stiffness is not None and max(result.fit.relative_discrepancy) < 30
    )


def test_a_spacing_or_scale_in_the_wrong_unit_is_refused_before_memory_runs_out(
    tmp_path: Path, capsys
):
    """A spacing of microns on a 3 cm organ (or a node count of 10^9, or a mesh read in mm as
    metres) would ask for terabytes of voxels: refused in one line naming the spacing, the
    mesh's size and the units, before anything is allocated; a scale that is not a number > 0
    is refused by name."""
    points = ball(0.03, 300, 600)
    mesh = meshio.Mesh(points, [("tetra", Delaunay(points).simplices)])
    options = dict(fix=["box:-1,-1,-1:1,1,-0.02"], forces=["nearest:0,0,0.03:0,0,-0.01"],
                   youngs_modulus=5000, poisson_ratio=0.45)  # fmt: skip
    for asked in ({"spacing": 1e-6}, {"nodes": 10**9}, {"spacing": 0.005, "scale": 1000.0}):
        with pytest.raises(MeshError, match=r"would span \d+ x \d+ x \d+ cells.*metres"):
            spec_from_mesh(mesh, **options, **asked)
    for scale in (float("nan"), 0.0, -1.0):
        with pytest.raises(ValueError, match="scale must be a finite number > 0"):
            spec_from_mesh(mesh, **options, spacing=0.006, scale=scale)
    path = tmp_path / "lobe.vtu"
    meshio.write(path, mesh)
    argv = ["spec", "from-mesh", str(path), "--spacing", "1e-6", "--fix", "box:-1,-1,-1:1,1,-0.02",
            "--force", "nearest:0,0,0.03:0,0,-0.01", "--E", "5000", "--nu", "0.45"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "1e-06 m" in err and "--scale" in err
