"""A spec's reference mesh in pieces, or with nodes numbered twice, by every path it reaches the
FEM: inline ``reference.mesh`` and ``reference.mesh_id`` (an upload), over REST and in process.

The lattice is one solid. Nodes at one point numbered twice (two blocks or regions exported
without merging) are joined where the FEM builds its mesh (:func:`fpm.model.tetrahedra.
merge_coincident`), as ``spec_from_mesh`` joins them: the spec is accepted and its reference is
the mesh's without the copies. Pieces not joined through shared faces that the lattice's cells
join are refused at submit with a 422 naming the field and one piece (a tetrahedron of it, its
size, its centre: :func:`fpm.model.tetrahedra.lattice_pieces`, the check ``spec_from_mesh``
makes), where the FEM job failed later ("the stiffness matrix is singular").
"""

from __future__ import annotations

import copy
import re
from typing import Any

import numpy as np
import pytest
from test_fuzz_meshes import grid_tetrahedra

import fpm
from fpm.fem.solution import FemError
from fpm.model.tetrahedra import lattice_pieces, merge_coincident

SIZE = np.array([0.06, 0.03, 0.03])
"""The solid: two 3 cm cubes side by side along x (m)."""
PIECE = r"the piece of tetrahedron 162 (48 tetrahedra, around [0.045, 0.015, 0.015] m)"
"""The second cube of :func:`touching_pieces`, as the refusal names it."""


def clean_mesh() -> dict[str, Any]:
    """The solid as one conforming mesh: 6 x 3 x 3 cells of 1 cm, 6 tetrahedra each."""
    nodes, tets = grid_tetrahedra((6, 3, 3), SIZE)
    return {"nodes": nodes.tolist(), "tetrahedra": tets.tolist()}


def numbered_twice() -> dict[str, Any]:
    """:func:`clean_mesh` with the nodes of the plane x = 3 cm numbered twice: the tetrahedra
    beyond it use the copies (appended), so the two halves share no node (as two regions
    exported without merging)."""
    nodes, tets = (np.asarray(v) for v in clean_mesh().values())
    plane = np.flatnonzero(np.isclose(nodes[:, 0], 0.03))
    copy_of = np.arange(len(nodes))
    copy_of[plane] = len(nodes) + np.arange(len(plane))
    beyond = nodes[tets].mean(axis=1)[:, 0] > 0.03
    tets[beyond] = copy_of[tets[beyond]]
    return {"nodes": np.vstack([nodes, nodes[plane]]).tolist(), "tetrahedra": tets.tolist()}


def touching_pieces() -> dict[str, Any]:
    """The first cube in 3^3 cells (162 tetrahedra), the second in 2^3 (48, from index 162):
    they touch along x = 3 cm, but their faces there do not match (no shared face)."""
    a, ta = grid_tetrahedra((3, 3, 3), np.full(3, 0.03))
    b, tb = grid_tetrahedra((2, 2, 2), np.full(3, 0.03))
    nodes = np.vstack([a, b + [0.03, 0.0, 0.0]])
    return {"nodes": nodes.tolist(), "tetrahedra": np.vstack([ta, tb + len(a)]).tolist()}


def spec(mesh: dict[str, Any] | None = None, mesh_id: str | None = None) -> dict[str, Any]:
    """A box lattice of the solid (1 cm cells), held at x = 0, pulled down at the far end;
    the reference on ``mesh`` (inline) or the upload ``mesh_id``, as given (refine 0)."""
    reference: dict[str, Any] = {"refine": 0}
    if mesh is not None:
        reference["mesh"] = mesh
    if mesh_id is not None:
        reference["mesh_id"] = mesh_id
    return {
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1000.0},
        "geometry": {"type": "box", "size": SIZE.tolist(), "nodes": [7, 4, 4]},
        "fixed": [{"face": "x-"}],
        "load_cases": [{"forces": [{"nearest": [0.06, 0.015, 0.03], "vector": [0, 0, -0.01]}]}],
        "annealing": {"chains": 1},
        "reference": reference,
    }


def test_nodes_numbered_twice_are_joined_and_pieces_named_by_the_shared_check():
    """:func:`merge_coincident` gives back the mesh without the copies, exactly;
    :func:`lattice_pieces` names the piece the lattice joins, and passes a piece it does not."""
    twice, clean = numbered_twice(), clean_mesh()
    nodes, tets, merged = merge_coincident(twice["nodes"], twice["tetrahedra"])
    assert merged == 16  # the 4 x 4 nodes of the plane x = 3 cm
    np.testing.assert_array_equal(nodes, clean["nodes"])
    np.testing.assert_array_equal(tets, clean["tetrahedra"])
    as_given = merge_coincident(clean["nodes"], clean["tetrahedra"])
    assert as_given[2] == 0 and as_given[1].tolist() == clean["tetrahedra"]
    problem = fpm.load_problem(spec(clean))
    centres = problem.nodes[problem.solid.elements()].mean(axis=1)
    x, t = (np.asarray(v) for v in touching_pieces().values())
    pieces = lattice_pieces(x, t, centres)
    assert pieces.cells.tolist() == [27, 27]
    message = pieces.joined_apart(x, t)
    assert message is not None and PIECE in message
    assert lattice_pieces(x, t, centres[centres[:, 0] < 0.03]).joined_apart(x, t) is None
    for mesh in (clean, twice):  # one solid: the copies' tetrahedra share faces by position
        m = (np.asarray(v) for v in mesh.values())
        assert lattice_pieces(*m, centres).cells.tolist() == [len(centres)]


def test_a_mesh_with_nodes_numbered_twice_is_solved_as_the_mesh_without_them():
    """In process, inline and as the upload ``reference.mesh_id`` names: the same reference as
    the clean mesh's (was "the stiffness matrix is singular": the half beyond x = 3 cm held by
    nothing)."""
    clean = fpm.solve_fem(fpm.load_problem(spec(clean_mesh()))).displacements
    assert np.abs(clean).max() > 0
    inline = fpm.solve_fem(fpm.load_problem(spec(numbered_twice()))).displacements
    np.testing.assert_array_equal(inline, clean)
    uploaded = fpm.solve_fem(
        fpm.load_problem(spec(mesh_id="0" * 64)), mesh=numbered_twice()
    ).displacements
    np.testing.assert_array_equal(uploaded, clean)


def assert_refused_naming_the_piece(answer: Any, field: str) -> None:
    assert answer.status_code == 422, answer.text
    body = answer.json()
    assert [e["field"] for e in body["errors"]] == [field], body
    message = body["errors"][0]["message"]
    assert PIECE in message and "2 pieces not joined through shared faces" in message, message
    assert f"{field}: " in body["detail"]


@pytest.mark.redis
@pytest.mark.parametrize("route", ["/v1/calibrations", "/v1/fem-references"])
def test_pieces_the_lattice_joins_are_422_at_submit_naming_one_inline(api, redis, route):
    """Was 202, the FEM job failing later ("the stiffness matrix is singular"); the clean mesh
    is accepted as before, and nothing is stored for the refused spec."""
    assert api.post(route, json=spec(clean_mesh())).status_code == 202
    keys = set(redis.keys())
    answer = api.post(route, json=spec(touching_pieces()))
    assert_refused_naming_the_piece(answer, "reference.mesh")
    assert set(redis.keys()) == keys


@pytest.mark.redis
@pytest.mark.parametrize("route", ["/v1/calibrations", "/v1/fem-references"])
def test_pieces_the_lattice_joins_are_422_at_submit_naming_one_by_mesh_id(api, redis, route):
    """The upload itself is fine (no lattice to join it yet: 201); a spec whose lattice joins
    its pieces is refused at ``reference.mesh_id`` (was 202); the clean upload is accepted."""
    clean = api.post("/v1/meshes", json=clean_mesh())
    assert clean.status_code == 201, clean.text
    assert api.post(route, json=spec(mesh_id=clean.json()["id"])).status_code == 202
    pieces = api.post("/v1/meshes", json=touching_pieces())
    assert pieces.status_code == 201, pieces.text
    answer = api.post(route, json=spec(mesh_id=pieces.json()["id"]))
    assert_refused_naming_the_piece(answer, "reference.mesh_id")


@pytest.mark.redis
def test_nodes_numbered_twice_over_rest_are_accepted_and_their_fem_is_the_clean_one(
    api, redis, run_workers
):
    """Inline and uploaded (the upload kept as sent: its id is the hash of what was sent):
    202, and the FEM job succeeds with the clean mesh's reference (it failed: "the stiffness
    matrix is singular")."""
    twice = numbered_twice()
    uploaded = api.post("/v1/meshes", json=twice)
    assert uploaded.status_code == 201, uploaded.text
    assert api.post("/v1/meshes", json=copy.deepcopy(twice)).json() == uploaded.json()
    submitted = [
        api.post("/v1/fem-references", json=spec(twice)),
        api.post("/v1/fem-references", json=spec(mesh_id=uploaded.json()["id"])),
    ]
    assert [s.status_code for s in submitted] == [202, 202], [s.text for s in submitted]
    run_workers()
    clean = fpm.solve_fem(fpm.load_problem(spec(clean_mesh()))).displacements
    for s in submitted:
        reference = api.get(s.headers["location"]).json()
        assert reference["status"] == "succeeded", reference.get("error")
        np.testing.assert_allclose(reference["displacements"], clean, rtol=1e-12, atol=0)
    calibration = api.post("/v1/calibrations", json=spec(twice))  # (not run here)
    assert calibration.status_code == 202, calibration.text


def test_pieces_the_lattice_joins_are_refused_in_process_before_the_solve():
    """In process (``fpm.solve_fem`` on a spec that never went through the service) the same
    check names the piece, where the solve failed on a singular stiffness matrix."""
    problem = fpm.load_problem(spec(touching_pieces()))
    with pytest.raises(FemError, match=r"reference\.mesh: .*" + re.escape(PIECE)):
        fpm.solve_fem(problem)
