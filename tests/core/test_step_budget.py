"""fpm.step_budget_us: the deepest perturbed list whose region step meets a frame budget (the
paper's penetration depth as its speed control, Sec. 3.1)."""

from pathlib import Path

import numpy as np
import pytest
from test_calibration import soft_box_spec

import fpm
from fpm.fitting import step_budget
from fpm.fitting.calibration import calibrate
from fpm.model.stiffness import continuum_start, model_stiffness

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def box():
    """The paper's cube (10^3 nodes, loaded at the top's centre: 9 layers to the bottom)."""
    problem = fpm.load_problem(ROOT / "examples/paper-material-a.json")
    return problem, model_stiffness(problem, continuum_start(problem))


def test_the_budget_depth_is_the_deepest_region_within_it(box, monkeypatch):
    """With a step's cost made its region's node count (a clock that does not wobble), the
    answer is the deepest depth whose largest region has at most the budget's nodes: one
    deeper has more; a budget under one layer's region answers depth 1, not met."""
    problem, stiffness = box
    monkeypatch.setattr(step_budget, "step_microseconds", lambda rt, f: float(rt.n_nodes))
    whole = step_budget.runtime_of(problem, stiffness, 1.0)
    loaded = [c.nodes for c in problem.all_cases]
    sizes = [max(len(whole.region(n, depth).nodes) for n in loaded) for depth in range(1, 8)]
    assert sizes == sorted(sizes) and sizes[0] < sizes[-1], sizes
    i = 3  # depth 4: its regions smaller than depth 5's
    answer = step_budget.budget_depth(problem, stiffness, None, sizes[i] + 0.5, 7)
    assert answer["depth"] == i + 1 and answer["met"] and answer["nodes"] == sizes[i]
    assert step_budget.budget_notes(answer) == []
    low = step_budget.budget_depth(problem, stiffness, None, sizes[0] - 1.0, 7)
    assert low["depth"] == 1 and not low["met"]
    assert "fpm.step_budget_us" in step_budget.budget_notes(low)[0]
    wide = step_budget.budget_depth(problem, stiffness, None, 1e9, 7)
    assert wide["depth"] == 7 and wide["met"]


def test_a_real_step_grows_with_its_region(box):
    """Timed for real: one layer's region steps faster than every layer's (the whole box)."""
    problem, stiffness = box
    whole = step_budget.runtime_of(problem, stiffness, 1.0)
    case = problem.load_cases[0]
    forces = case.dense(problem.n_nodes)
    one = whole.region(case.nodes, 1)
    every = whole.region(case.nodes, None)
    assert len(one.nodes) < len(every.nodes) == problem.n_nodes
    small = step_budget.step_microseconds(one.runtime, one.forces(forces))
    large = step_budget.step_microseconds(every.runtime, every.forces(forces))
    assert 0 < small < large


def test_a_calibration_with_a_budget_reports_its_depth_and_judges_there():
    """A calibration given a budget returns the depth it allows (at most the depth 'auto'
    would resolve), the microseconds and the machine, in the result and its stored form; its
    validation figures are at that depth."""
    problem = fpm.load_problem(soft_box_spec(step_budget_us=1e9))
    ref = fpm.solve_fem(problem).displacements
    result = calibrate(problem, reference=ref)
    budget = result.parameters.step_budget
    assert budget is not None and budget.met and budget.depth == result.parameters.depth
    assert budget.backend in ("native", "numba", "numpy") and "cores" in budget.machine
    stored = result.to_dict()
    assert stored["step_budget"]["depth"] == result.parameters.depth
    from fpmcal.result_table import result_table

    table = result_table(problem, result)
    assert "meets the 1,000,000,000 us budget" in table and budget.machine in table
    tight = fpm.load_problem(soft_box_spec(step_budget_us=1e-3))
    cut = calibrate(tight, reference=ref)
    assert cut.parameters.depth == 1 and not cut.parameters.step_budget.met
    assert any("fpm.step_budget_us" in w for w in cut.warnings)
    assert np.isfinite(cut.fit.relative_discrepancy).all()
