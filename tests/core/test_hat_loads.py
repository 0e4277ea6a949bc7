"""A nodal force as the load it stands for (``fpm.loads: "hat"``, :mod:`fpm.model.hat_loads`),
and a lattice held where the spec holds the organ (:func:`fpm.io.meshes.voxelise.support_planes`).

The shares are checked against the closed form of the consistent mass matrix on a regular
lattice (1D rows [1/6, 2/3, 1/6] in the volume, their tensor products; [1/6, 2/3, 1/6] x
[1/6, 2/3, 1/6] on a face), their sum and first moment, and the FEM reference must keep
loading the forces as given."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
from pydantic import ValidationError

import fpm
from fpm.io.meshes import spec_from_mesh
from fpm.io.meshes.voxelise import lattice, support_planes
from fpm.model.geometry import box_hexahedra, box_nodes
from fpm.model.hat_loads import hat_shares
from fpm.model.spec import BoxGeometry

ROW = np.array([1 / 6, 2 / 3, 1 / 6])
"""The 1D consistent mass row of an interior node on a uniform lattice, divided by its sum."""


def box(shape: tuple[int, int, int] = (5, 5, 5), h: float = 0.01):
    g = BoxGeometry(type="box", size=[h * (n - 1) for n in shape], nodes=shape)
    return box_nodes(g), box_hexahedra(shape)


def shares_around(nodes, hexahedra, node: int) -> np.ndarray:
    """(3, 3, 3) shares of a force on ``node`` of a 5^3 lattice on the nodes around it."""
    row = hat_shares(nodes, hexahedra, np.array([node])).getrow(node).toarray().ravel()
    i, j, k = node % 5, (node // 5) % 5, node // 25
    out = np.zeros((3, 3, 3))
    for n in np.flatnonzero(row):
        a, b, c = n % 5 - i + 1, (n // 5) % 5 - j + 1, n // 25 - k + 1
        out[a, b, c] = row[n]
    return out


def test_an_interior_force_is_shared_as_the_consistent_mass_row():
    nodes, hexahedra = box()
    centre = 2 + 5 * (2 + 5 * 2)
    got = shares_around(nodes, hexahedra, centre)
    assert np.allclose(got, np.einsum("a,b,c->abc", ROW, ROW, ROW), atol=1e-12)
    assert got[1, 1, 1] == pytest.approx(8 / 27)


def test_a_surface_force_stays_on_the_surface_four_ninths_at_its_node():
    nodes, hexahedra = box()
    top = 2 + 5 * (2 + 5 * 4)  # the middle of the top face
    got = shares_around(nodes, hexahedra, top)
    assert np.allclose(got[:, :, 1], np.outer(ROW, ROW), atol=1e-12)
    assert not got[:, :, 0].any() and not got[:, :, 2].any()  # nothing into the volume
    assert got[1, 1, 1] == pytest.approx(4 / 9)


def test_shares_keep_the_resultant_and_on_a_flat_face_the_point_of_action():
    rng = np.random.default_rng(3)
    nodes, hexahedra = box((6, 5, 4), 0.007)
    nodes = nodes + 0.001 * rng.standard_normal(nodes.shape) * (nodes[:, 2:] > 0)  # bumps
    loaded = np.arange(len(nodes))
    shares = hat_shares(nodes, hexahedra, loaded)
    assert np.allclose(np.asarray(shares.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    flat, _ = box((6, 5, 4), 0.007)
    top = np.flatnonzero(
        (flat[:, 2] == flat[:, 2].max())
        & (np.abs(flat[:, 0] - flat[:, 0].mean()) < 0.01)
        & (np.abs(flat[:, 1] - flat[:, 1].mean()) < 0.005)
    )  # away from the face's edges
    flat_shares = hat_shares(flat, hexahedra, top)
    for node in top:
        row = flat_shares.getrow(node)
        assert np.allclose(row.data @ flat[row.indices], flat[node], atol=1e-12)


def pressed_box() -> dict:
    """A 4 cm box held at z-, pressed at the middle of its top face (one node)."""
    return {
        "name": "hat",
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1000.0},
        "geometry": {"type": "box", "size": [0.04, 0.04, 0.04], "nodes": [5, 5, 5]},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"name": "press", "forces": [{"at": [0.02, 0.02, 0.04],
                                                     "vector": [0, 0, -0.01]}]}],
    }  # fmt: skip


def test_the_lattice_takes_the_shares_and_the_reference_the_forces_as_given():
    spec = {**pressed_box(), "fpm": {"loads": "hat"}}
    problem = fpm.load_problem(spec)
    (case,) = problem.load_cases
    assert len(case.nodes) == 9 and np.allclose(case.forces.sum(axis=0), [0, 0, -0.01])
    assert len(case.as_given().nodes) == 1
    spec["reference"] = {"refine": 1}
    node = fpm.load_problem({**spec, "fpm": {"loads": "node"}})
    hat = fpm.load_problem(spec)
    # the reference loads the forces as given: the same FEM solution either way
    assert np.allclose(
        fpm.solve_fem(node).displacements, fpm.solve_fem(hat).displacements, rtol=0, atol=1e-15
    )
    # node loads against a reference that spreads them: a note says so and what 'hat' does
    assert any("fpm.loads = 'node'" in n for n in node.notes)
    assert not any("fpm.loads" in n for n in hat.notes)
    # 'auto', the default: 'hat' where the reference spreads the forces, the paper's node
    # loads where it loads them at their nodes ("check": the mesh as given)
    auto = fpm.load_problem({**spec, "fpm": {}})
    assert auto.spec.fpm.loads == "auto" and auto.loads == hat.loads == "hat"
    assert node.loads == "node"
    assert auto.spec.model_dump(mode="json")["fpm"]["loads"] == "auto"  # stored as asked
    assert [c.nodes.tolist() for c in auto.load_cases] == [c.nodes.tolist() for c in hat.load_cases]
    assert not any("fpm.loads" in n for n in auto.notes)
    unrefined = fpm.load_problem({**spec, "fpm": {}, "reference": {}})
    assert unrefined.loads == "node" and not any("fpm.loads" in n for n in unrefined.notes)
    assert len(unrefined.load_cases[0].nodes) == 1


def test_hat_loads_on_a_spring_network_are_refused_at_the_field():
    spec = {
        "name": "net",
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.3, "density": 1000.0},
        "geometry": {"type": "network", "nodes": [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]],
                     "springs": [[0, 1], [0, 2], [1, 2]], "masses": 0.001},
        "fixed": [{"node": 0}],
        "load_cases": [{"forces": [{"node": 1, "vector": [0, 0.001, 0]}]}],
        "fpm": {"loads": "hat", "stiffness": "single"},
    }  # fmt: skip
    with pytest.raises(ValidationError, match=r"fpm\.loads"):
        fpm.load_problem(spec)


def test_the_lattice_puts_a_node_plane_on_a_held_box_face():
    lo, hi = np.array([-0.07, -0.045, -0.035]), np.array([0.07, 0.045, 0.035])
    origin, cells = lattice(lo, hi, 0.0065)  # centred: 11 cells along z, planes at +-3.25 mm
    assert not np.any(np.isclose(origin[2] + 0.0065 * np.arange(cells[2] + 1), 0.0))
    planes = support_planes([{"box": [[-1, -1, -1], [1, 1, 0.0]]}, {"face": "z-"}])
    origin, cells = lattice(lo, hi, 0.0065, planes)
    z = origin[2] + 0.0065 * np.arange(cells[2] + 1)
    assert np.isclose(z, 0.0, atol=1e-12).sum() == 1
    assert z[0] <= lo[2] and z[-1] >= hi[2] and z[1] > lo[2] and z[-2] < hi[2]  # no spare cell
    assert np.allclose(origin[:2], lattice(lo, hi, 0.0065)[0][:2])  # the box's +-1 miss the solid


def test_an_organ_from_its_mesh_is_held_where_the_spec_holds_it_and_takes_hat_loads():
    from bench.tet_organ import organ_mesh

    nodes, tets = organ_mesh((5, 4, 4))
    spec, notes = spec_from_mesh(
        meshio.Mesh(nodes, [("tetra", tets)]), fix=["box:-1,-1,-1:1,1,0"],
        forces=["nearest:0,0,0.035:0,0,-0.01"], spacing=0.0065, youngs_modulus=5e3,
        poisson_ratio=0.45, density=1040.0,
    )  # fmt: skip
    assert spec["fpm"]["loads"] == "hat" and any("fpm.loads = 'hat'" in n for n in notes)
    problem = fpm.load_problem(spec)
    held = problem.nodes[problem.fixed]
    assert held[:, 2].max() == pytest.approx(0.0, abs=1e-12)
    on_plane = np.abs(problem.nodes[:, 2]) < 1e-12
    assert on_plane.sum() > 50  # a whole plane of the lattice, not a surface node by chance


def test_the_paper_s_node_loads_by_name_from_the_command_line(tmp_path):
    from bench.tet_organ import organ_mesh
    from fpmcal.cli import main

    nodes, tets = organ_mesh((4, 3, 4))
    path = tmp_path / "organ.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("tetra", tets)]))
    argv = ["spec", "from-mesh", str(path), "--spacing", "0.01", "--fix", "face:z-",
            "--force", "nearest:0,0,0.035:0,0,-0.01", "--E", "5000", "--nu", "0.45"]  # fmt: skip
    assert main([*argv, "-o", str(tmp_path / "hat.json")]) == 0
    assert main([*argv, "--loads", "node", "-o", str(tmp_path / "node.json")]) == 0
    hat = fpm.load_problem(str(tmp_path / "hat.json"))
    node = fpm.load_problem(str(tmp_path / "node.json"))
    assert hat.spec.fpm.loads == "hat" and node.spec.fpm.loads == "node"
    assert len(node.load_cases[0].nodes) == 1 < len(hat.load_cases[0].nodes)
    assert any("fpm.loads = 'node'" in n for n in node.notes)  # the reference spreads it


def test_a_spec_stored_before_auto_keeps_the_node_loads_it_was_fitted_with():
    """The service stores the dumped spec; before 'auto' the dump left 'node' out, so a stored
    spec without fpm.loads was fitted with node loads and is rebuilt so (its exports too),
    while one stored now says 'auto' and takes the hat where the reference spreads forces."""
    from fpm.model.spec import ProblemSpec
    from worker.problems import problem_of

    spec = {**pressed_box(), "reference": {"refine": 1}}
    dumped = ProblemSpec.model_validate(spec).model_dump(mode="json")
    assert dumped["fpm"]["loads"] == "auto"
    assert problem_of(None, dumped).loads == "hat"  # type: ignore[arg-type]  (no tagged mesh)
    del dumped["fpm"]["loads"]  # as the service dumped it before 'auto'
    old = problem_of(None, dumped)  # type: ignore[arg-type]
    assert old.loads == "node" and len(old.load_cases[0].nodes) == 1
    dumped["fpm"]["loads"] = "hat"  # an explicit choice is kept
    assert problem_of(None, dumped).loads == "hat"  # type: ignore[arg-type]
