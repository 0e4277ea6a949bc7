"""Real organs with the defaults: the lattice follows the organ's surface, bad meshes are refused
with the cell and the place (422 over REST, never a 500), parts one cell thick are modelled,
and a force at a point of the surface acts there, spread over its cell's nodes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import meshio
import numpy as np
import pytest
from pydantic import ValidationError

import fpm
from client import spec_from_mesh as sdk_spec_from_mesh
from fpm.io.meshes import MeshError, spec_from_mesh
from fpm.model.geometry import thin_cells, thin_parts
from fpmcal.cli import main
from tests.core.test_meshes import kuhn_box

MATERIAL = {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040.0}


def organ() -> meshio.Mesh:
    """The bench's organ, coarse (288 tetrahedra, 14 x 9 x 7 cm)."""
    from bench.tet_organ import organ_mesh

    nodes, tets = organ_mesh((4, 3, 4))
    return meshio.Mesh(nodes, [("tetra", tets)])


GIVEN = dict(
    fix=["face:z-"], forces=["nearest:0,0,0.035:0,0,-0.01"], spacing=0.01, **MATERIAL
)  # fmt: skip


# --- 1. the lattice follows the organ by default ---------------------------------------------


def test_a_tetrahedral_mesh_gets_the_conforming_lattice_and_voxels_by_name(tmp_path: Path):
    mesh = organ()
    spec, notes = spec_from_mesh(mesh, **GIVEN)
    assert spec["geometry"]["type"] == "mesh" and "mesh" in spec["reference"]
    assert any("surface nodes moved onto the mesh's surface" in n for n in notes)
    voxels, notes = spec_from_mesh(mesh, lattice="voxels", **GIVEN)
    assert voxels["geometry"]["type"] == "voxels"
    assert any("lattice: the voxels (--lattice voxels)" in n for n in notes)
    with pytest.raises(MeshError, match="lattice 'cubes': use one of conforming, voxels"):
        spec_from_mesh(mesh, lattice="cubes", **GIVEN)
    path = tmp_path / "organ.vtu"
    meshio.write(path, mesh)
    sdk = sdk_spec_from_mesh(path, lattice="voxels", **GIVEN)
    assert sdk["geometry"] == voxels["geometry"]
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.01", "--fix", "face:z-",
            "--force", GIVEN["forces"][0], "--E", "5000", "--nu", "0.45", "--density", "1040",
            "--lattice", "voxels", "-o", str(tmp_path / "v.json")]  # fmt: skip
    assert main(argv) == 0
    assert fpm.load_problem(str(tmp_path / "v.json")).spec.geometry.type == "voxels"


def test_an_organ_loaded_in_two_patterns_gets_the_stiffness_field(tmp_path: Path):
    """The stiffness default of a spec made from a tetrahedral organ: the field where there is
    another load to judge it on (it is returned only where it predicts a left-out pattern
    better), families+volume for one pattern (a scaled copy is the same pattern), and what
    the user names, by the library, the SDK and the CLI."""
    mesh = organ()
    one = dict(GIVEN, forces=[GIVEN["forces"][0], "nearest:0,0,0.035:0,0,-0.02"])
    spec, notes = spec_from_mesh(mesh, **one)
    assert "stiffness" not in spec["fpm"]  # the schema's default: families+volume
    assert any("one force pattern" in n for n in notes)
    two = dict(GIVEN, forces=[GIVEN["forces"][0], "nearest:0,0,0.035:0.01,0,0"])
    spec, notes = spec_from_mesh(mesh, **two)
    assert spec["fpm"]["stiffness"] == "field"
    assert any("fpm.stiffness = 'field'" in n for n in notes)
    assert fpm.load_problem(spec).spec.fpm.stiffness == "field"
    named, _ = spec_from_mesh(mesh, stiffness="families", **two)
    assert named["fpm"]["stiffness"] == "families"
    voxels, _ = spec_from_mesh(mesh, voxel_reference=True, **two)  # no tetrahedra to judge on
    assert "stiffness" not in voxels["fpm"]
    path = tmp_path / "organ.vtu"
    meshio.write(path, mesh)
    assert sdk_spec_from_mesh(path, **two)["fpm"]["stiffness"] == "field"
    assert sdk_spec_from_mesh(path, stiffness="single", **two)["fpm"]["stiffness"] == "single"
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.01", "--fix", "face:z-",
            "--E", "5000", "--nu", "0.45", "--stiffness", "families+volume",
            "-o", str(tmp_path / "s.json")]  # fmt: skip
    argv += [a for f in two["forces"] for a in ("--force", f)]
    assert main(argv) == 0
    assert fpm.load_problem(str(tmp_path / "s.json")).spec.fpm.stiffness == "families+volume"


def test_the_conforming_lattice_folds_no_voxel_step_onto_the_surface():
    """Each surface node goes out along its normal: no surface face gets two corners closer
    than 0.4 h (to the nearest point, 8-10% of the organ's faces did, down to 0.24 h), no
    surface node stays far from the mesh's surface, every cell keeps KEPT_JACOBIAN of its
    voxel's."""
    from fpm.fem.elasticity import min_jacobian_determinants
    from fpm.fem.samples import boundary_hexahedron_faces, lattice_surface
    from fpm.io.meshes.conform import KEPT_JACOBIAN
    from fpm.model.tetrahedra import TetMesh

    mesh = organ()
    h = 0.007
    spec, _ = spec_from_mesh(mesh, **{**GIVEN, "spacing": h})
    voxels, _ = spec_from_mesh(mesh, lattice="voxels", **{**GIVEN, "spacing": h})
    x = np.array(spec["geometry"]["nodes"])
    hexahedra = np.array(spec["geometry"]["hexahedra"])
    corners, _, _ = boundary_hexahedron_faces(hexahedra)
    pairs = np.linalg.norm(x[corners][:, :, None] - x[corners][:, None], axis=3)
    assert pairs[pairs > 0].min() > 0.4 * h
    surface = lattice_surface(hexahedra, len(x))
    _, _, off = TetMesh(mesh.points, mesh.cells_dict["tetra"]).nearest_on_boundary(x[surface])
    assert off.max() < 0.3 * h  # held back by the Jacobian rule at most this (nearest: 0.62 h)
    before = min_jacobian_determinants(fpm.load_problem(voxels).solid.nodes[hexahedra])
    assert np.all(min_jacobian_determinants(x[hexahedra]) >= KEPT_JACOBIAN * before * (1 - 1e-9))


def test_a_line_crosses_a_triangle_where_it_should():
    from fpm.io.meshes.conform import line_crossings

    triangle = np.array(
        [[[0.0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0.0, 0, -2], [1, 0, -2], [0, 1, -2]]]
    )
    points = np.array([[0.2, 0.2, 0.0], [0.2, 0.2, 0.0], [2.0, 2.0, 0.0]])
    up = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    t = line_crossings(points, up, triangle)
    assert t[0] == pytest.approx(1.0) and t[1] == pytest.approx(-1.0)  # the nearer, either side
    assert np.isinf(t[2])  # misses both


def test_inverted_tetrahedra_are_renumbered_with_a_note():
    mesh = organ()
    tets = mesh.cells[0].data.copy()
    flipped = tets.copy()
    flipped[[3, 40, 41]] = flipped[[3, 40, 41]][:, [1, 0, 2, 3]]
    spec, _ = spec_from_mesh(meshio.Mesh(mesh.points, [("tetra", tets)]), **GIVEN)
    repaired, notes = spec_from_mesh(meshio.Mesh(mesh.points, [("tetra", flipped)]), **GIVEN)
    assert any("3 tetra cells numbered inside out (negative volume: 3, 40, 41)" in n for n in notes)
    np.testing.assert_allclose(repaired["geometry"]["nodes"], spec["geometry"]["nodes"], atol=1e-12)
    assert repaired["geometry"]["hexahedra"] == spec["geometry"]["hexahedra"]
    same = [sorted(map(sorted, s["reference"]["mesh"]["tetrahedra"])) for s in (spec, repaired)]
    assert same[0] == same[1]


def test_a_flat_tetrahedron_is_refused_naming_the_cell(tmp_path: Path, capsys):
    mesh = organ()
    points = np.vstack([mesh.points, mesh.points[[0, 1, 2]].mean(axis=0)])  # on face 0-1-2
    tets = np.vstack([mesh.cells[0].data, [[0, 1, 2, len(points) - 1]]])
    flat = meshio.Mesh(points, [("tetra", tets)])
    with pytest.raises(MeshError, match=rf"tetra cell {len(tets) - 1} .* is degenerate"):
        spec_from_mesh(flat, **GIVEN)
    meshio.write(tmp_path / "flat.vtu", flat)
    argv = ["spec", "from-mesh", str(tmp_path / "flat.vtu"), "--spacing", "0.01", "--fix",
            "face:z-", "--force", "face:z+:0,0,-1", "--E", "5000", "--nu", "0.45"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"tetra cell {len(tets) - 1}" in err[0] and "one plane" in err[0]


def plate(thickness: float) -> meshio.Mesh:
    """A 6 x 6 cm plate of the given thickness (m), tetrahedralised."""
    points, tets, _ = kuhn_box([0, 0, 0], [0.06, 0.06, thickness], 3)
    points[:, 2] = points[:, 2] * (thickness / points[:, 2].max())
    return meshio.Mesh(points, [("tetra", tets)])


def test_a_spacing_that_leaves_a_part_one_cell_thick_is_modelled_not_refused():
    """A 8 mm plate at h = 10 mm is one cell thick everywhere: the conforming lattice refines it
    to two cells of 5 mm (a graded lattice, named in the notes); the voxels as they are load
    with a warning naming the part and its place. The organ's tips, a few thin cells each, are
    not parts."""
    given = dict(GIVEN, fix=["box:-1,-1,-1:0.011,1,1"], forces=["face:z+:0,0,-0.1:distribute"])
    spec, notes = spec_from_mesh(plate(0.008), **given)
    assert any(n.startswith("graded lattice: part 1 one cell thick") for n in notes), notes
    problem = fpm.load_problem(spec)
    assert problem.warnings == [] and thin_parts(problem.solid.elements()) == []
    voxels, _ = spec_from_mesh(plate(0.008), lattice="voxels", **given)
    warned = fpm.load_problem(voxels).warnings
    assert len(warned) == 1 and "one cell thick over a part of 36 cells around" in warned[0]
    assert "modelled as it is" in warned[0]
    problem = fpm.load_problem(spec_from_mesh(organ(), **GIVEN)[0])
    hexahedra = problem.solid.elements()
    assert 0 < thin_cells(hexahedra).sum() and thin_parts(hexahedra) == []


def test_bad_organ_specs_are_422_naming_the_field_over_rest(api):
    given = dict(GIVEN, fix=["box:-1,-1,-1:0.011,1,1"], forces=["face:z+:0,0,-0.1"])
    spec, _ = spec_from_mesh(plate(0.008), lattice="voxels", **dict(given, spacing=0.004))
    # the same plate's voxels at 10 mm, one cell thick: modelled (with a warning), not refused
    spec["geometry"].update(occupancy=[[[1]] * 6] * 6, spacing=[0.01] * 3, origin=[0, 0, 0])
    answer = api.post("/v1/calibrations", json=spec)
    assert answer.status_code == 202, answer.text
    good, _ = spec_from_mesh(organ(), **GIVEN)
    mesh = good["reference"]["mesh"]
    mesh["tetrahedra"][7] = [mesh["tetrahedra"][7][i] for i in (0, 1, 2, 2)]
    answer = api.post("/v1/calibrations", json=good)
    assert answer.status_code == 422, answer.text
    assert "reference.mesh.tetrahedra.7" in [e["field"] for e in answer.json()["errors"]]


# --- 2. loads where the user puts them ---------------------------------------------------------


def test_a_surface_point_spreads_by_shape_functions_with_linear_precision():
    """On a box lattice and on the organ's conforming lattice: the weights are >= 0, sum to 1
    and reproduce the nearest surface point (partition of unity, linear precision); a point at
    a node gives that node alone; a point on the surface is its own nearest point."""
    from fpm.model.geometry import surface_point
    from fpm.model.tetrahedra import TetMesh

    rng = np.random.default_rng(3)
    box = fpm.load_problem(
        {
            "material": MATERIAL,
            "geometry": {"type": "box", "size": [0.04, 0.03, 0.02], "nodes": [5, 4, 3]},
            "fixed": [{"face": "z-"}],
            "load_cases": [{"forces": [{"face": "z+", "vector": [0, 0, 1]}]}],
        }
    )
    hexahedra = box.solid.elements()
    for _ in range(20):
        size = np.array([0.04, 0.03, 0.02])
        p = rng.uniform(0, 1, 3) * size
        side = rng.integers(3)
        p[side] = size[side] * rng.integers(2)  # on one of the box's sides
        found = surface_point(box.nodes, hexahedra, p)
        assert found.weights.min() >= 0 and found.weights.sum() == pytest.approx(1, abs=1e-14)
        np.testing.assert_allclose(found.weights @ box.nodes[found.nodes], found.point, atol=1e-15)
        assert found.distance < 1e-12
    corner = surface_point(box.nodes, hexahedra, box.nodes[7])
    assert corner.nodes[corner.weights > 0].tolist() == [7]
    assert corner.weights.max() == 1.0
    problem = fpm.load_problem(spec_from_mesh(organ(), **GIVEN)[0])
    mesh = organ()
    _, surface, _ = TetMesh(mesh.points, mesh.cells[0].data).nearest_on_boundary(
        rng.uniform(-0.08, 0.08, (30, 3))
    )
    for p in surface:
        found = surface_point(problem.nodes, problem.solid.elements(), p)
        assert found.weights.min() >= 0 and found.weights.sum() == pytest.approx(1, abs=1e-14)
        np.testing.assert_allclose(found.weights @ problem.nodes[found.nodes], found.point)
        assert found.distance < 0.35 * 0.01  # the conforming lattice's surface is near the mesh's


def test_a_force_at_a_point_acts_there_and_a_far_point_is_refused(api):
    """The load case's nodal forces sum to the force and their moment is the point's (the
    spread centroid is the surface point); a point 2 h from the organ is refused with its
    distance, at load_cases.0.forces.0.point, by load_problem and over REST (422)."""
    from fpm.model.tetrahedra import TetMesh

    mesh = organ()
    at = TetMesh(mesh.points, mesh.cells[0].data).nearest_on_boundary(
        np.array([[0.02, 0.01, 0.04]])
    )[1][0]
    force = "point:" + ",".join(map(repr, at.tolist())) + ":0,0,-0.01"
    spec, _ = spec_from_mesh(mesh, **dict(GIVEN, forces=[force]))
    assert spec["load_cases"][0]["forces"] == [{"point": at.tolist(), "vector": [0, 0, -0.01]}]
    problem = fpm.load_problem(spec)
    assert problem.spec.fpm.loads == "hat"  # the lattice takes its nodes' hats (test_hat_loads)
    np.testing.assert_allclose(problem.load_cases[0].forces.sum(axis=0), [0, 0, -0.01], atol=1e-17)
    case = problem.load_cases[0].as_given()  # the point's spread over its face, as the spec says
    assert 2 <= len(case.nodes) <= 4
    np.testing.assert_allclose(case.forces.sum(axis=0), [0, 0, -0.01], atol=1e-17)
    centroid = case.forces[:, 2] @ problem.nodes[case.nodes] / case.forces[:, 2].sum()
    assert any("acts at" in n for n in problem.notes)
    assert np.linalg.norm(centroid - at) < 0.1 * 0.01  # the lattice's surface near the mesh's
    spec["load_cases"][0]["forces"][0]["point"] = [0.0, 0.0, 0.06]  # 2.6 cm above the top
    with pytest.raises(ValidationError) as raised:
        fpm.load_problem(spec)
    error = raised.value.errors()[0]
    assert error["loc"] == ("load_cases", 0, "forces", 0, "point")
    found = re.search(
        r"is ([0-9.]+) m from the solid's surface \(nearest surface point (\[.*?\])\)", error["msg"]
    )
    assert found, error["msg"]  # the distance, and the nearest point it was measured to
    nearest = np.array(json.loads(found[2]))
    assert float(found[1]) == pytest.approx(np.linalg.norm(nearest - [0, 0, 0.06]), rel=2e-3)
    assert 0.024 < float(found[1]) < 0.027  # 2.6 cm above the top
    answer = api.post("/v1/calibrations", json=spec)
    assert answer.status_code == 422, answer.text
    assert "load_cases.0.forces.0.point" in [e["field"] for e in answer.json()["errors"]]
    with pytest.raises(ValueError, match="'point' places a force"):
        from fpm.io.meshes import parse_selector

        parse_selector("point:0,0,0")
