"""fpm.fitting.damping.validation.geometry_notes: a validation case whose figure is mostly the
springs' change of geometry (large loads against the linear FEM reference) says so, with the
figure the same model has under small loads; a case in the linear range does not."""

import copy
import json
import re
from pathlib import Path

import numpy as np
import pytest

import fpm
from fpm.fitting.damping.settings import DEFAULT
from fpm.fitting.damping.validation import validate
from tests.core.test_export import soft_block_spec

GEOMETRY_GAP = DEFAULT.geometry_gap

THETA = [30.0, 20.0, 4.0, 2e4]  # k per family, N/m, and kappa, Pa: a soft block's


def block(scale: float):
    """The soft block with two validation presses, every force times ``scale``, and its FEM
    reference (linear: its displacements are proportional to the loads)."""
    spec = copy.deepcopy(soft_block_spec())
    press = {"at": [0.02, 0.02, 0.04], "vector": [0, 0, -0.002]}
    sideways = {"at": [0.01, 0.02, 0.04], "vector": [0, 0.002, 0]}
    spec["validation_cases"] = [
        {"name": "press off centre", "forces": [press]},
        {"name": "sideways", "forces": [sideways]},
    ]
    for case in spec["load_cases"] + spec["validation_cases"]:
        for force in case["forces"]:
            force["vector"] = [scale * v for v in force["vector"]]
    problem = fpm.load_problem(spec)
    return problem, fpm.solve_fem(problem)


def test_a_case_in_the_linear_range_gets_no_note():
    problem, reference = block(1.0)
    found = validate(problem, reference, THETA, None)
    assert found.notes == [] and len(found.relative) == 2


def test_a_large_load_is_said_to_be_the_springs_geometry_with_its_small_load_figure():
    problem, reference = block(100.0)
    found = validate(problem, reference, THETA, None)
    small_problem, small_reference = block(0.1)  # the same cases 1,000 times smaller: linear
    small = validate(small_problem, small_reference, THETA, None)
    assert small.notes == []
    assert len(found.notes) >= 1
    for note in found.notes:
        name, big, little, gap = re.match(
            r"validation case '(.+)': ([\d.]+)% at its loads, ([\d.]+)% under small loads: "
            r"([\d.]+) points are the springs' change of geometry",
            note,
        ).groups()
        j = [c.name for c in problem.validation_cases].index(name)
        assert float(big) == pytest.approx(found.relative[j], abs=0.05)
        assert float(little) == pytest.approx(small.relative[j], abs=0.05)
        assert float(gap) > GEOMETRY_GAP
    assert np.any(np.array(found.relative) - np.array(small.relative) > GEOMETRY_GAP)


def test_geometry_false_leaves_the_notes_out():
    problem, reference = block(100.0)
    assert validate(problem, reference, THETA, None, geometry=False).notes == []


def test_a_calibration_without_validation_cases_says_its_figures_flatter_it():
    """Every figure of a fit of several stiffness parameters with no validation cases is on
    its own loads: the result says so, unless the paper's model (one k) or method (which judge
    the fit on its own loads, as the paper does) was asked for."""
    from fpm.fitting.calibration import unseen_note

    spec = copy.deepcopy(soft_block_spec())
    spec.pop("validation_cases", None)
    (note,) = unseen_note(fpm.load_problem(spec))
    assert "no validation cases" in note and "validation_cases" in note
    assert unseen_note(block(1.0)[0]) == []
    for paper in ({"fpm": {**spec.get("fpm", {}), "stiffness": "single"}},
                  {"annealing": {**spec.get("annealing", {}), "method": "paper"}}):  # fmt: skip
        assert unseen_note(fpm.load_problem({**spec, **paper})) == []


def test_the_note_reaches_the_result_and_not_the_papers():
    spec = json.loads((Path(__file__).parents[2] / "examples" / "small-box.json").read_text())
    assert spec["fpm"]["stiffness"] == "single" and "validation_cases" not in spec
    result = fpm.calibrate(fpm.load_problem(spec))
    assert not any(w.startswith("no validation cases") for w in result.warnings)
    spec["fpm"]["stiffness"] = "families"
    result = fpm.calibrate(fpm.load_problem(spec))
    assert any(w.startswith("no validation cases") for w in result.warnings)
