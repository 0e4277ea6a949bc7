"""A d search that settles nothing with the product's own dt and step cap keeps the static fit:
the stiffness and every figure stand, d is the critical-damping estimate, and the result says
so (fpm.fitting.damping.stage.unfitted_damping); with a dt or cap the spec names, the failure
and its advice are the answer."""

import numpy as np
import pytest
from test_calibration import soft_box_spec

import fpm
from fpm.fitting.calibration import calibrate
from fpm.fitting.damping import stage
from fpm.fitting.damping.unsettled import DampingError, Hopeless


@pytest.fixture(scope="module")
def box():
    problem = fpm.load_problem(soft_box_spec())
    return problem, fpm.solve_fem(problem).displacements


def test_a_search_that_settles_nothing_keeps_the_static_fit(box, monkeypatch):
    problem, ref = box
    fitted = calibrate(problem, reference=ref)
    assert fitted.settle.settled and not any("damping not fitted" in w for w in fitted.warnings)

    def too_slow(*args, **kwargs):
        raise Hopeless("load case 'probe' does not settle: its decay predicts 3,000,000 steps")

    monkeypatch.setattr(stage, "fit_damping", too_slow)
    kept = calibrate(problem, reference=ref)
    assert kept.parameters.stiffness == fitted.parameters.stiffness  # stage 1 and the polish
    assert kept.parameters.depth == fitted.parameters.depth
    assert kept.fit.static_cost == fitted.fit.static_cost
    # the figures are the static equilibria's: what a settled run reaches
    assert np.allclose(kept.fit.relative_discrepancy, fitted.fit.relative_discrepancy, rtol=1e-3)
    assert not kept.settle.settled and kept.run.damping_runs == 0
    assert kept.fit.verdict.grade != "good"
    note = next(w for w in kept.warnings if w.startswith("damping not fitted"))
    assert "3,000,000 steps" in note and "an estimate" in note
    # d is the critical-damping estimate: within a few times the fitted one, never a bound
    assert 0.1 < kept.parameters.d / fitted.parameters.d < 10


def test_with_the_spec_s_own_cap_the_failure_is_the_answer(box, monkeypatch):
    problem, ref = box
    capped = fpm.load_problem(soft_box_spec(max_steps=5))

    def none_settles(*args, **kwargs):
        raise DampingError("no d in [1e-06, 1] settles every load case within max_steps 5")

    monkeypatch.setattr(stage, "fit_damping", none_settles)
    with pytest.raises(DampingError, match="max_steps 5"):
        calibrate(capped, reference=ref)


def test_a_lattice_predicted_too_slow_is_not_searched(box, monkeypatch):
    """Where the modes predict more steps than fpm.max_steps 'auto' allows (here the ceiling
    lowered under the box's prediction), no run is made: the fit keeps the predicted d."""
    from fpm.fitting.damping import choice

    problem, ref = box
    monkeypatch.setattr(choice, "AUTO_CEILING", 10)
    kept = calibrate(problem, reference=ref)
    note = next(w for w in kept.warnings if w.startswith("damping not fitted"))
    assert "over the 10 fpm.max_steps 'auto' allows" in note
    assert kept.run.damping_runs == 0 and not kept.settle.settled
    assert kept.parameters.d == kept.settle.d_predicted
