"""The problem spec: the examples load, and every bad spec is refused with a ValidationError whose
``loc`` names the offending field and whose message says why."""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_fpm import box_spec, lattice_index, network_spec, spec_errors

import fpm

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("paper-material-*.json"))

UNIT_CUBE = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
"""The 8 corners of the unit cube in fpm.model.hexahedron order (0-3 bottom, 4-7 top)."""


def mesh_spec(hexahedron: list[int]) -> dict[str, Any]:
    """One unit-cube hexahedron given explicitly, bottom fixed, top corner 6 pulled up."""
    spec = box_spec((2, 2, 2), forces=[{"node": 6, "vector": [0, 0, 1.0]}])
    spec["geometry"] = {"type": "mesh", "nodes": UNIT_CUBE, "hexahedra": [hexahedron]}
    return spec


def broken(spec: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    """A deep copy of ``spec`` with the item at ``path`` replaced by ``value``."""
    out = copy.deepcopy(spec)
    target = out
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return out


def only_error(spec: Any) -> tuple[tuple[Any, ...], str]:
    errors = spec_errors(spec)
    assert len(errors) == 1, errors
    return errors[0]


# --- what must load ------------------------------------------------------------------------


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_examples_load_as_the_paper_describes(path: Path):
    """Table 1 setup: 10x10x10 nodes of a 0.1 m cube, face z=0 fixed, four central nodes of the
    face z=0.1 pulled along +z, three load cases."""
    assert EXAMPLES, "no examples/paper-material-*.json"
    problem = fpm.load_problem(path)
    assert problem.n_nodes == 1000
    assert problem.h == pytest.approx(0.1 / 9)
    assert problem.fixed.sum() == 100
    assert np.all(problem.nodes[problem.fixed, 2] == 0.0)
    assert len(problem.load_cases) == 3
    shape = (10, 10, 10)
    central = sorted(lattice_index(shape, i, j, 9) for i in (4, 5) for j in (4, 5))
    for case in problem.load_cases:
        assert case.nodes.tolist() == central
        assert np.all(case.forces[:, :2] == 0) and np.all(case.forces[:, 2] > 0)
    # The same file read as a JSON string and as a dict gives the same problem.
    text = path.read_text()
    for source in (text, json.loads(text)):
        again = fpm.load_problem(source)
        assert np.array_equal(again.nodes, problem.nodes)
        assert np.array_equal(again.fixed, problem.fixed)


def test_no_fixed_nodes_is_a_valid_spec_for_simulation():
    """``"fixed": []``: a free two-node spring pulled apart by +-F settles at extension F/k."""
    f, k = 0.02, 10.0  # extension 2 mm, well inside the 10 mm solid
    spec = network_spec(
        [[0, 0, 0], [0.01, 0, 0]],
        [(0, 1)],
        forces={0: [-f, 0, 0], 1: [f, 0, 0]},
        fpm_settings={"settle_tolerance": 1e-10, "max_steps": 20000},
    )
    assert spec["fixed"] == []
    problem = fpm.load_problem(spec)
    assert not problem.fixed.any()
    result = fpm.simulate(problem, k=k, d=0.5)
    assert result.settled
    u = result.displacements
    assert u[1, 0] - u[0, 0] == pytest.approx(f / k, rel=1e-7)
    # (The node-by-node sweep does not conserve momentum exactly, so the free pair drifts a
    # little while it settles: only the stretch is fixed by the mathematics.)
    assert np.all(u[:, 1:] == 0)


# --- what must be refused, and where ------------------------------------------------------

BOX = box_spec((3, 3, 3))  # 27 nodes (0..26), 0.01 m apart; face z- fixed; force at node 18


@pytest.mark.parametrize(
    ("path", "value", "loc", "reason"),
    [
        (("fixed", 0), {"face": "w+"}, ("fixed", 0, "face"), "'x-'"),
        (("fixed", 0), {"face": "top"}, ("fixed", 0, "face"), "'z+'"),
        (
            ("load_cases", 0, "forces", 0, "at"),
            [0.005, 0.0, 0.02],
            ("load_cases", 0, "forces", 0, "at"),
            "no node at",
        ),
        (("load_cases", 0, "forces"), [], ("load_cases", 0, "forces"), "at least 1"),
        (("material", "poisson_ratio"), 0.5, ("material", "poisson_ratio"), "less than 0.5"),
        (("material", "poisson_ratio"), 0.7, ("material", "poisson_ratio"), "less than 0.5"),
        (("material", "poisson_ratio"), -1.0, ("material", "poisson_ratio"), "greater than -1"),
        (("material", "density"), -1040.0, ("material", "density"), "greater than 0"),
        (("material", "density"), 0.0, ("material", "density"), "greater than 0"),
        (
            ("load_cases", 0, "forces", 0),
            {"node": 27, "vector": [0, 0, 1]},
            ("load_cases", 0, "forces", 0, "node"),
            "out of range (0..26)",
        ),
        (("fixed", 0), {"node": 27}, ("fixed", 0, "node"), "out of range (0..26)"),
        (
            ("load_cases", 0, "forces", 0, "vector", 2),
            math.nan,
            ("load_cases", 0, "forces", 0, "vector", 2),
            "finite",
        ),
        (("material", "youngs_modulus"), math.nan, ("material", "youngs_modulus"), "finite"),
        (("material", "youngs_modulus"), math.inf, ("material", "youngs_modulus"), "finite"),
        (("geometry", "size", 1), math.nan, ("geometry", "box", "size", 1), "finite"),
        (("fpm", "gravity"), [0, math.nan, 0], ("fpm", "gravity", 1), "finite"),
        (("material", "desnity"), 1040.0, ("material", "desnity"), "Extra inputs"),
        (("fpm", "max_step"), 10, ("fpm", "max_step"), "Extra inputs"),
        (("loadcases",), [], ("loadcases",), "Extra inputs"),
    ],
    ids=[
        "unknown-face",
        "unknown-face-word",
        "at-no-node",
        "no-forces",
        "poisson-0.5",
        "poisson-0.7",
        "poisson--1",
        "negative-density",
        "zero-density",
        "force-node-range",
        "fixed-node-range",
        "nan-force",
        "nan-E",
        "inf-E",
        "nan-size",
        "nan-gravity",
        "typo-material",
        "typo-fpm",
        "typo-top-level",
    ],
)
def test_bad_spec_names_the_field_and_the_reason(path, value, loc, reason):
    error_loc, message = only_error(broken(BOX, path, value))
    assert error_loc == loc
    assert reason in message


def test_nan_in_json_text_is_refused():
    """JSON has no NaN, but Python's json module reads the token ``NaN``: refuse it too."""
    text = json.dumps(broken(BOX, ("load_cases", 0, "forces", 0, "vector", 0), math.nan))
    assert "NaN" in text
    loc, message = only_error(text)
    assert loc == ("load_cases", 0, "forces", 0, "vector", 0)
    assert "finite" in message


def test_a_nan_among_network_masses_is_refused():
    spec = network_spec(
        [[0, 0, 0], [1, 0, 0]], [(0, 1)], masses=[1.0, math.nan], forces={1: [1, 0, 0]}
    )
    # masses is float | list[float]: pydantic reports why each member of the union failed.
    errors = dict(spec_errors(spec))
    assert errors[("geometry", "network", "masses", "list[float]", 1)] == (
        "Input should be a finite number"
    )


def test_mesh_hexahedron_node_out_of_range():
    loc, message = only_error(mesh_spec([0, 1, 2, 3, 4, 5, 6, 8]))
    assert loc == ("geometry", "hexahedra", 0)
    assert "out of range (0..7)" in message


def test_mesh_hexahedron_repeated_node():
    loc, message = only_error(mesh_spec([0, 1, 2, 3, 4, 5, 6, 6]))
    assert loc == ("geometry", "hexahedra", 0)
    assert "distinct" in message


def test_mesh_hexahedron_negative_node_index():
    loc, message = spec_errors(mesh_spec([0, 1, 2, 3, 4, 5, 6, -1]))[0]
    assert loc[:3] == ("geometry", "hexahedra", 0)
    assert "range" in message or "greater than or equal to 0" in message


def test_mesh_node_in_no_hexahedron_is_refused():
    spec = mesh_spec(list(range(8)))
    spec["geometry"]["nodes"] = [*UNIT_CUBE, [2, 2, 2]]  # node 8: in no hexahedron, mass 0
    spec["load_cases"][0]["forces"] = [{"node": 8, "vector": [0, 0, 1.0]}]
    loc, _ = spec_errors(spec)[0]
    assert loc[0] in ("geometry", "load_cases")


@pytest.mark.parametrize("pair", [(0, 2), (-1, 1)], ids=["past-end", "negative"])
def test_network_spring_node_out_of_range(pair):
    spec = network_spec(
        [[0, 0, 0], [1, 0, 0]], [(0, 1), pair], fixed_nodes=[0], forces={1: [1, 0, 0]}
    )
    loc, message = only_error(spec)
    assert loc == ("geometry", "springs", 1)
    assert "out of range (0..1)" in message


def test_every_error_is_reported_not_just_the_first():
    spec = broken(BOX, ("material", "density"), -1.0)
    spec = broken(spec, ("fixed", 0), {"face": "w+"})
    locs = {loc for loc, _ in spec_errors(spec)}
    assert locs == {("material", "density"), ("fixed", 0, "face")}


def test_force_on_a_fixed_node_is_refused():
    spec = broken(BOX, ("load_cases", 0, "forces", 0), {"node": 0, "vector": [0, 0, 1]})
    loc, message = only_error(spec)
    assert loc == ("load_cases", 0, "forces", 0)
    assert "fixed" in message


def test_cli_bad_spec_exits_2_and_names_the_field(tmp_path: Path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(broken(BOX, ("material", "poisson_ratio"), 0.5)))
    run = subprocess.run(
        [sys.executable, "-m", "fpmcal.cli", "simulate", str(path), "--k", "1", "--d", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert run.returncode == 2
    assert "material.poisson_ratio" in run.stderr
    assert "less than 0.5" in run.stderr
    assert run.stdout == ""


def test_every_example_loads():
    for path in sorted((ROOT / "examples").glob("*.json")):
        assert fpm.load_problem(path).n_nodes > 0, path.name


# --- selectors: nearest, forces on faces and boxes, distribute ------------------------------


def test_nearest_takes_the_nearest_node_and_reports_how_far_it_is():
    point = [0.0104, 0.0197, 0.0203]  # nearest lattice point (1, 2, 2): node 25
    spec = broken(BOX, ("load_cases", 0, "forces", 0), {"nearest": point, "vector": [0, 0, 1]})
    spec["fixed"].append({"nearest": [0.021, -0.003, 0.0095]})  # lattice point (2, 0, 1): node 11
    problem = fpm.load_problem(spec)
    assert problem.load_cases[0].nodes.tolist() == [25]
    assert problem.fixed[11] and problem.fixed.sum() == 10
    distance = float(np.linalg.norm(problem.nodes[25] - point))
    assert distance == pytest.approx(math.sqrt(0.4**2 + 0.3**2 + 0.3**2) * 1e-3)
    assert (
        f"load_cases.0.forces.0.nearest: node 25 at [0.01, 0.02, 0.02] is {distance * 1e3:.3g} mm "
        "from the point" in problem.notes
    )
    assert any(
        n.startswith("fixed.1.nearest: node 11 at [0.02, 0, 0.01] is ") for n in problem.notes
    )


def test_at_still_needs_a_node_and_points_to_nearest():
    spec = broken(BOX, ("load_cases", 0, "forces", 0, "at"), [0.0104, 0.0197, 0.0203])
    loc, message = only_error(spec)
    assert loc == ("load_cases", 0, "forces", 0, "at")
    assert "no node at" in message and "nearest node 25" in message and '"nearest"' in message


def test_distribute_splits_the_vector_evenly_over_the_selected_nodes():
    vector = [0.3, -0.6, 0.9]
    spec = broken(BOX, ("load_cases", 0, "forces", 0), {"face": "z+", "vector": vector})
    spec["load_cases"][0]["forces"][0]["distribute"] = True
    case = fpm.load_problem(spec).load_cases[0]
    assert case.nodes.tolist() == list(range(18, 27))  # the 9 nodes of face z+
    assert np.all(case.forces == np.asarray(vector) / 9)  # an equal share each, bit for bit
    assert case.forces.sum(axis=0) == pytest.approx(vector, rel=1e-14)
    # A box of 4 top nodes: the total force is still the vector.
    spec["load_cases"][0]["forces"][0] = {
        "box": [[0, 0, 0.02], [0.01, 0.01, 0.02]],
        "vector": vector,
        "distribute": True,
    }
    case = fpm.load_problem(spec).load_cases[0]
    assert case.nodes.tolist() == [18, 19, 21, 22]
    assert np.all(case.forces == np.asarray(vector) / 4)
    assert case.forces.sum(axis=0).tolist() == vector


def test_face_and_box_forces_without_distribute_put_the_vector_on_each_node():
    vector = [0.0, 0.0, 0.05]
    spec = broken(BOX, ("load_cases", 0, "forces", 0), {"face": "z+", "vector": vector})
    spec["load_cases"][0]["forces"].append(
        {"box": [[0, 0, 0.02], [0.0, 0.01, 0.02]], "vector": vector}
    )
    problem = fpm.load_problem(spec)
    case = problem.load_cases[0]
    assert case.nodes.tolist() == list(range(18, 27))
    expected = np.tile(vector, (9, 1))
    expected[[0, 3]] *= 2  # nodes 18 and 21 are also in the box: forces on a node add up
    assert np.array_equal(case.forces, expected)
    assert any(
        n.startswith("load_cases.0.forces.0.face: 9 nodes each get [0, 0, 0.05] N (total")
        and '"distribute": true' in n
        for n in problem.notes
    )


def test_fixed_nodes_of_a_loaded_face_take_no_force():
    """Face x+ of BOX: 3 of its 9 nodes are on the fixed face z-; the force goes to the other 6."""
    spec = broken(
        BOX,
        ("load_cases", 0, "forces", 0),
        {"face": "x+", "vector": [0.6, 0, 0], "distribute": True},
    )
    problem = fpm.load_problem(spec)
    case = problem.load_cases[0]
    assert len(case.nodes) == 6 and not problem.fixed[case.nodes].any()
    assert case.forces.sum(axis=0) == pytest.approx([0.6, 0, 0])
    assert (
        "load_cases.0.forces.0.face: 3 of its 9 nodes are fixed and take no force" in problem.notes
    )


@pytest.mark.parametrize(
    ("force", "loc", "reason"),
    [
        ({"face": "z-", "vector": [0, 0, 1]}, ("load_cases", 0, "forces", 0), "all 9 nodes"),
        (
            {"box": [[1, 1, 1], [2, 2, 2]], "vector": [0, 0, 1]},
            ("load_cases", 0, "forces", 0, "box"),
            "selects no node",
        ),
        (
            {"box": [[0.02, 0, 0], [0, 0.02, 0.02]], "vector": [0, 0, 1]},
            ("load_cases", 0, "forces", 0, "box"),
            "low corner first",
        ),
        (
            {"node": 20, "face": "z+", "vector": [0, 0, 1]},
            ("load_cases", 0, "forces", 0),
            "exactly one of face, node, at, nearest, box, point (got face, node)",
        ),
        ({"vector": [0, 0, 1]}, ("load_cases", 0, "forces", 0), "(got none)"),
        (
            {"nearest": [0, 0, 0], "vector": [0, 0, 1]},
            ("load_cases", 0, "forces", 0),
            "node 0 is fixed",
        ),
    ],
    ids=["all-fixed", "empty-box", "reversed-box", "two-targets", "no-target", "nearest-fixed"],
)
def test_bad_force_targets_name_the_field(force, loc, reason):
    error_loc, message = only_error(broken(BOX, ("load_cases", 0, "forces", 0), force))
    assert error_loc == loc
    assert reason in message


def test_a_fixed_box_with_no_node_names_the_field():
    loc, message = only_error(broken(BOX, ("fixed", 0), {"box": [[1, 1, 1], [2, 2, 2]]}))
    assert loc == ("fixed", 0, "box")
    assert "selects no node" in message and "move or widen the box" in message


def test_a_schedule_of_infinitely_many_moves_is_refused_not_crashed():
    """beta = 5e-324 (found by the API fuzzer) makes (1/t_final - 1/t_initial) / beta inf."""
    from fpm.model.spec import MOVES_CAP, lundy_mees_moves

    assert lundy_mees_moves(0.05, 2e-3, 5e-324) == MOVES_CAP
    with pytest.raises(ValueError, match="moves per chain"):
        fpm.ProblemSpec.model_validate(
            {**json.loads((ROOT / "examples" / "small-box.json").read_text()),
             "annealing": {"beta": 5e-324}}
        )  # fmt: skip
