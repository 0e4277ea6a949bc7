"""bench.export_solve: the independent solve of the JSON export, nonlinear and linearised at
rest (the small-load limit the organ rows report beside their figures)."""

import json

import numpy as np
import pytest

import fpm
from bench import export_solve
from fpm.io.export import export
from tests.core.test_export import soft_block_spec


@pytest.fixture(scope="module")
def model():
    problem = fpm.load_problem(soft_block_spec())
    record = {"stiffness": {"axis": 30.0, "face": 20.0, "body": 4.0}, "volume_stiffness": 2e4,
              "d": 0.05, "depth": 10, "dt": 1e-4}  # fmt: skip
    forces = [case.dense(problem.n_nodes) for case in problem.load_cases]
    return json.loads(export(problem, record, "json")), forces


def test_linearised_at_rest_is_the_small_load_limit(model):
    """The nonlinear equilibrium over the load scale tends to the linearised one, its gap
    shrinking in proportion to the load (the springs' rotation and stretch are of first order
    in the load), case by case."""
    exported, forces = model
    for f in forces:
        linear = export_solve.solve(exported, f, nonlinear=False)
        gaps = [
            np.abs(export_solve.solve(exported, s * f) / s - linear).max() / np.abs(linear).max()
            for s in (1e-2, 1e-3)
        ]
        assert gaps[1] < 1e-5
        assert gaps[0] / gaps[1] == pytest.approx(10, rel=0.1)


def test_a_press_on_a_soft_block_is_not_linear(model):
    """At the loads given (a 2 mN press on a 5 kPa block of 1 cm cells) the two part ways:
    what the organ rows' 'linearised' figure separates from the reported one."""
    exported, forces = model
    for f in forces:
        linear = export_solve.solve(exported, 50 * f, nonlinear=False)
        full = export_solve.solve(exported, 50 * f)
        assert export_solve.relative(full, linear) > 1.0
