"""Settled means near the static equilibrium (fpm.dynamics.settle): on lattices small
enough to solve exactly, a run that settles on the distance criterion (the bound) or on the
target criterion (the fit's runs) is within the promised distance of the exact static
solution, at two sizes, and stays there; the settle distance 'auto' is a share of the case's
own discrepancy; the mode stiffness is K's lowest eigenvalue; and the criterion does not move
with the load's scale."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

import fpm
from fpm.dynamics.eigen import lowest_modes
from fpm.dynamics.equilibrium import StaticSolver
from fpm.dynamics.modes import predict_damping
from fpm.dynamics.settle import (
    FLOOR,
    NOMINAL,
    SHARE,
    by_distance,
    case_distances,
    estimated_distance,
    measured_distance,
    mode_stiffness,
    nodal_size,
    nominal_distance,
)
from fpm.dynamics.simulation import fpm_model
from fpm.dynamics.stability import stable_time_step
from fpm.dynamics.step_caps import case_models
from fpm.fitting.bounds import damping_bounds
from fpm.fitting.damping.lockstep import run_case
from fpm.model.stiffness import continuum_start, model_stiffness


def bar(nodes_x: int, force: float = 1e-3) -> fpm.Problem:
    """A soft bar 0.1 x 0.03 x 0.03 m at spacing 0.1 / (nodes_x - 1), fixed at x-, pressed
    down (``force`` N) at the top of its free end: families+volume, nu 0.45, a spec that names
    no fpm settings (its slow modes bend it; 1 mm under the default force)."""
    h = 0.1 / (nodes_x - 1)
    across = round(0.03 / h) + 1
    size = [0.1, 0.03, 0.03]
    return fpm.load_problem(
        {
            "name": "bar",
            "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040.0},
            "geometry": {"type": "box", "size": size, "nodes": [nodes_x, across, across]},
            "fixed": [{"face": "x-"}],
            "load_cases": [
                {"forces": [{"nearest": [0.1, size[1] / 2, size[2]], "vector": [0, 0, -force]}]}
            ],
        }
    )


def exact_static(problem: fpm.Problem, stiffness) -> np.ndarray:
    """(N, 3) the static equilibrium solved to a force tolerance of 1e-12, m."""
    solver = StaticSolver(problem)
    return solver.solve(0, stiffness, None, tolerance=1e-12).displacements


@pytest.mark.parametrize("nodes_x", [11, 21])
def test_a_settled_run_is_within_the_promised_distance_of_the_exact_equilibrium(nodes_x):
    problem = bar(nodes_x)
    assert by_distance(problem.spec)  # a spec that names no fpm settings
    theta = continuum_start(problem)
    stiffness = model_stiffness(problem, theta)
    dt = 0.5 * stable_time_step(problem, stiffness)
    (model,) = case_models(problem, stiffness, None, dt)
    prediction, _ = predict_damping(
        problem, StaticSolver(problem), stiffness, None, dt, damping_bounds(problem)
    )
    run = fpm.simulate(problem, k=stiffness, d=prediction.d, dt=dt, max_steps=200_000)
    assert run.settled
    exact = exact_static(problem, stiffness)
    # the bound (1) is in 2-norms
    measured = float(np.linalg.norm(run.displacements - exact) / np.linalg.norm(exact))
    promised = nominal_distance(problem.spec)
    assert promised == NOMINAL  # settle_distance 'auto' with no reference to read
    estimated = estimated_distance(run.residual, float(np.linalg.norm(run.displacements)),
                                   model.mode_stiffness)  # fmt: skip
    # the run stopped on its estimate, which bounds the distance it measures
    assert estimated < promised
    assert measured <= estimated
    assert 0 < measured < promised


@pytest.mark.parametrize("nodes_x", [11, 21])
@pytest.mark.parametrize("slower", [1.0, 0.95])
def test_the_target_criterion_settles_within_its_distance_and_stays(nodes_x, slower):
    """The fit's runs settle towards the static equilibrium they know: the settled state is
    within its distance of the exact solution (in the calibration's norm, the sum of nodal
    distances), and stays within it as the run goes on, at the fastest d and at 0.95 times it
    (underdamped, near the lowest d at which the step stays stable: the run swings
    through the equilibrium, which the velocities' term of the reach does not call settled)."""
    problem = bar(nodes_x)
    theta = continuum_start(problem)
    stiffness = model_stiffness(problem, theta)
    dt = 0.5 * stable_time_step(problem, stiffness)
    (model,) = case_models(problem, stiffness, None, dt)
    exact = exact_static(problem, stiffness)
    distance = 0.01
    prediction, _ = predict_damping(
        problem, StaticSolver(problem), stiffness, None, dt, damping_bounds(problem)
    )
    d = slower * prediction.d
    run = run_case(fpm_model(problem), stiffness, None, dt, 0, d, 200_000,
                   NOMINAL * model.mode_stiffness, exact, distance)  # fmt: skip
    assert run.finished and not run.diverged
    assert 0 < measured_distance(run.displacements, exact) < distance
    assert run.history[-1][1] < distance * nodal_size(exact)
    # go on from the settled state, never settling: it stays within the distance
    going = fpm_model(problem).start(0, k=stiffness, d=d, depth=None, dt=dt,
                                     settle_tolerance=0.0)  # fmt: skip
    going.advance(run.steps)
    worst = 0.0
    for _ in range(40):
        going.advance(max(run.steps // 20, 1))
        worst = max(worst, measured_distance(going.result().displacements, exact))
    assert worst < distance


def test_auto_distance_is_a_share_of_the_cases_discrepancy_together():
    """SHARE of sum |u* - u_ref| / sum |u*| over every case, the same for each: a case fitted
    exactly settles no closer than the others; clipped to [FLOOR, NOMINAL]."""
    problem = bar(11)
    static = np.zeros((3, problem.n_nodes, 3))
    static[:, :, 2] = -1e-3
    static[2] *= 2.0  # twice the displacement: twice the weight
    reference = static.copy()
    reference[0] *= 1.10  # 10% off
    reference[1] *= 1.0000001  # a perfect fit
    reference[2] *= 1.05  # 5% off
    together = (0.10 * 1 + 1e-7 * 1 + 0.05 * 2) / (1 + 1 + 2)
    assert case_distances(problem.spec, static, reference) == pytest.approx([SHARE * together] * 3)
    assert case_distances(problem.spec, static, static * 1.0000001) == pytest.approx([FLOOR] * 3)
    assert case_distances(problem.spec, static, static * 2.0) == pytest.approx([NOMINAL] * 3)
    assert case_distances(problem.spec, static, None) == [NOMINAL] * 3
    spec = problem.spec.model_dump()
    spec["fpm"]["settle_distance"] = 0.002
    named = fpm.load_problem(spec)
    assert case_distances(named.spec, static, reference) == [0.002] * 3


def test_the_mode_stiffness_is_the_lowest_eigenvalue_of_the_tangent():
    """With every mode kept the Rayleigh-Ritz value is exact; with the 16 slowest it is within
    a few per cent (K's softest vector lies nearly in their span)."""
    problem = bar(11)
    stiffness = model_stiffness(problem, continuum_start(problem))
    solver = StaticSolver(problem)
    system, _ = solver.system(0, None)
    tangent = system.tangent(np.zeros((system.n_free, 3)), system.parameters(stiffness),
                             modified=True)  # fmt: skip
    masses = problem.solid.masses[system.free]
    lowest = float(sla.eigvalsh(tangent.toarray(), subset_by_index=[0, 0])[0])
    every = lowest_modes(tangent, masses, tangent.shape[0])
    assert mode_stiffness(every.w2, every.shapes) == pytest.approx(lowest, rel=1e-8)
    slowest = lowest_modes(tangent, masses, 16)
    assert lowest <= mode_stiffness(slowest.w2, slowest.shapes) <= 1.05 * lowest


def test_the_criterion_does_not_move_with_the_load_scale():
    """Linear in the load: a ten times larger force settles in the same steps, and its state
    is ten times the displacement (the force criterion is also relative to the load; the
    distance criterion is relative to the displacement, and both scale alike)."""
    runs = []
    for force in (1e-5, 1e-4):
        problem = bar(11, force)
        stiffness = model_stiffness(problem, continuum_start(problem))
        runs.append(fpm.simulate(problem, k=stiffness, d=0.02))
    assert runs[0].settled and runs[1].settled
    assert abs(runs[0].steps - runs[1].steps) <= 0.02 * runs[0].steps
    np.testing.assert_allclose(runs[1].displacements, 10 * runs[0].displacements, rtol=0.05,
                               atol=0.01 * np.abs(runs[1].displacements).max())  # fmt: skip


def test_a_named_settle_tolerance_keeps_the_force_criterion():
    problem = bar(11)
    spec = problem.spec.model_dump()
    spec["fpm"]["settle_tolerance"] = 1e-5
    named = fpm.load_problem(spec)
    assert not by_distance(named.spec)
    stiffness = model_stiffness(named, continuum_start(named))
    run = fpm.simulate(named, k=stiffness, d=0.02)
    assert run.settled
    # the force criterion: the largest unbalanced nodal force below 1e-5 x the applied force
    assert run.residual < 1e-5 * 1e-3
