"""One stage numbering and the spec's case names wherever a calibration is shown: the service's
stages (store.status.calibration_stages), fpm-client's bar and status, fpmcal's bar."""

from __future__ import annotations

import pytest

from client.cli import show_calibration
from client.progress import render
from fpmcal.progress import _Bar
from store.status import Phase, calibration_stages


def test_the_fem_reference_is_always_stage_one():
    assert calibration_stages("two-stage") == [
        Phase.FEM,
        Phase.ANNEALING,
        Phase.DAMPING,
        Phase.FINALIZE,
    ]
    assert calibration_stages("paper") == [Phase.FEM, Phase.ANNEALING, Phase.FINALIZE]


def calibration(**progress: object) -> dict:
    base = {
        "phase": "annealing",
        "method": "two-stage",
        "stage": "stage 2 of 4: stiffness search (annealing on static equilibria)",
        "stages": ["fem", "annealing", "damping", "finalize"],
        "stage_number": 2,
        "iterations": 5,
        "total_iterations": 10,
    }
    return {"id": "c1", "name": "box", "status": "running", "progress": {**base, **progress}}


def test_the_bar_and_the_status_give_the_services_number():
    running = calibration()
    assert " stage 2/4 stiffness" in render(running)
    assert "stage       stage 2 of 4: stiffness search" in show_calibration(running)
    damping = calibration(phase="damping", stage="stage 3 of 4: damping (starting)", stage_number=3)
    assert " stage 3/4 damping" in render(damping)


RESULT = {
    "method": "two-stage",
    "k": 30.0,
    "stiffness": {"axis": 30.0, "face": 12.5, "body": 4.0},
    "d": 0.13,
    "depth": 3,
    "full_depth": 3,
    "relative_discrepancy": [20.0, 22.0],
    "loaded_discrepancy": [10.0, 12.0],
    "discrepancy_h": [0.5, 1.0],
    "settle_steps": [130, 140],
    "h": 0.01,
    "warnings": ["load case 'press on top': the largest FEM displacement ..."],
}


def test_status_names_the_load_cases_as_the_spec_does():
    done = calibration(phase="done", stage="done", stage_number=None)
    done.update(
        status="succeeded",
        result=RESULT,
        parameter_set_id="p1",
        load_cases=["press on top", "load case 2"],
    )
    text = show_calibration(done)
    assert "press on top " in text and "load case 2 " in text
    assert "load case 1" not in text


def test_fpmcals_best_cost_is_the_best_over_all_chains(capsys: pytest.CaptureFixture[str]):
    """Chain 0 reaches 0.2; chain 1 starts at 0.9: the bar keeps 0.2 (it showed 0.9)."""
    bar = _Bar(chains=2, moves=10)
    for move, cost in ((5, 0.5), (10, 0.2)):
        bar({"phase": "annealing", "chain": 0, "move": move, "temperature": 1.0, "best_cost": cost})
    bar({"phase": "annealing", "chain": 1, "move": 5, "temperature": 1.0, "best_cost": 0.9})
    costs = [float(line.split("best cost ")[1]) for line in capsys.readouterr().err.splitlines()]
    assert costs == [0.5, 0.2, 0.2]
