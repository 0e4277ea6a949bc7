"""The web view's profile panel (worker/profile.py) for every stiffness mode: the stored result
becomes simulate's parameters through the one function that does it
(:func:`fpm.model.stiffness.fitted_theta`), and the panel's FPM curve is the run at exactly those
parameters (for families+volume it once failed: "give 4 values, not 1")."""

import json
from pathlib import Path

import numpy as np
import pytest

from fpm import load_problem, simulate, solve_fem
from fpm.model.stiffness import continuum_start, fitted_theta, stiffness_dict, volume_stiffness
from worker.profile import profile_data

SPEC = json.loads((Path(__file__).resolve().parents[2] / "examples/small-box.json").read_text())


def stored_result(problem, theta: list[float]) -> dict:
    """A result as the worker stores it (k, stiffness per family, kappa, d, depth, figures)."""
    e, h = problem.spec.material.youngs_modulus, problem.h
    n = len(problem.load_cases)
    return {
        "k": float(theta[0]),
        "stiffness": stiffness_dict(problem, theta),
        "volume_stiffness": volume_stiffness(problem, theta),
        "d": float(np.sqrt(e * h * problem.solid.masses.mean())),
        "depth": 3,
        "relative_discrepancy": [5.0] * n,
        "loaded_discrepancy": [6.0] * n,
        "discrepancy_h": [1.0] * n,
    }


@pytest.mark.parametrize("mode", ["single", "families", "families+volume"])
def test_profile_panel_renders_for_every_stiffness_mode(mode):
    spec = {**SPEC, "geometry": {**SPEC["geometry"], "connectivity": "axis+face"}}
    problem = load_problem({**spec, "fpm": {"stiffness": mode}})
    mu_h = problem.spec.material.youngs_modulus / (2 * 1.45) * problem.h
    theta = {
        "single": [mu_h],
        "families": [mu_h, 0.7 * mu_h],
        "families+volume": continuum_start(problem),
    }[mode]
    result = stored_result(problem, theta)
    assert fitted_theta(problem, result) == pytest.approx(theta, rel=1e-15)
    reference = solve_fem(problem).displacements
    panel = profile_data(problem, reference, result)
    assert len(panel) == len(problem.load_cases)
    for j, case in enumerate(panel):
        run = simulate(problem, k=theta, d=result["d"], depth=3, load_case=j)
        line = case["nodes"]
        assert len(line) >= 4 and case["settled"]
        assert case["fpm"] == pytest.approx(np.linalg.norm(run.displacements[line], axis=1))
        assert case["fem"] == pytest.approx(np.linalg.norm(reference[j][line], axis=1))
        assert max(case["fpm"]) > 0


def test_fitted_theta_reads_objects_and_refuses_what_the_mode_lacks():
    problem = load_problem({**SPEC, "fpm": {"stiffness": "families+volume"}})
    theta = continuum_start(problem)

    class Result:
        k = theta[0]
        stiffness = stiffness_dict(problem, theta)
        volume_stiffness = theta[-1]

    assert fitted_theta(problem, Result()) == theta
    with pytest.raises(ValueError, match="kappa"):
        fitted_theta(problem, {"k": 1.0, "stiffness": stiffness_dict(problem, theta)})
    single = load_problem({**SPEC, "fpm": {"stiffness": "single"}})
    assert fitted_theta(single, {"stiffness": {"axis": 2.0, "face": 2.0}}) == [2.0]
    with pytest.raises(ValueError, match="one k per family"):
        fitted_theta(single, {"stiffness": {"axis": 2.0, "face": 3.0}})
