"""The slowest modes found ahead, beside the polish (fpm.dynamics.modes_ahead): the same modes
the prediction would find on the same hierarchy, bit for bit, and the same prediction; none
for a list whose hierarchy was replaced since, nor for a list of other nodes."""

from __future__ import annotations

import numpy as np

import fpm
from fpm.dynamics.equilibrium import StaticSolver
from fpm.dynamics.modes import predict_damping
from fpm.dynamics.modes_ahead import ModesAhead
from fpm.fitting.bounds import damping_bounds
from fpm.model.stiffness import continuum_start, model_stiffness
from tests.core.test_spectrum import box


def solved(problem: fpm.Problem) -> tuple[StaticSolver, object]:
    """A static solver whose lists have a multigrid hierarchy (a linear solve built it)."""
    solver = StaticSolver(problem, amg_from=0)
    stiffness = model_stiffness(problem, continuum_start(problem))
    for j in range(len(problem.load_cases)):
        solver.linear_response(j, stiffness, None, solver.loads(j))
    return solver, stiffness


def test_modes_found_ahead_are_the_prediction_s_own():
    """Both load cases share one list: one set of modes, found on the thread, equal to the
    bit to those the prediction finds itself, and the prediction made with them is the same."""
    problem = box((11, 5, 5), "families+volume")
    solver, stiffness = solved(problem)
    ahead = ModesAhead(solver, None)
    ahead.start(1)
    found = ahead.modes(None)
    assert len(found) == 1
    dt = 1e-4
    bounds = damping_bounds(problem)
    mine, _ = predict_damping(problem, solver, stiffness, None, dt, bounds)
    theirs, models = predict_damping(problem, solver, stiffness, None, dt, bounds, modes=found)
    assert theirs.d == mine.d and theirs.steps == mine.steps
    (modes,) = found.values()
    again = {}
    predict_damping(problem, solver, stiffness, None, dt, bounds, modes=again)
    assert again == {}  # the caller's dict is not filled in
    key = next(iter(found))
    from fpm.dynamics.modes import reduced_steps

    fresh: dict[bytes, object] = {}
    reduced_steps(problem, solver, stiffness, None, dt, modes=fresh)
    np.testing.assert_array_equal(fresh[key].shapes, modes.shapes)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(fresh[key].w2, modes.w2)  # type: ignore[attr-defined]
    assert len(models) == 2


def test_a_replaced_hierarchy_drops_its_modes_and_another_list_takes_none():
    problem = box((11, 5, 5), "families+volume")
    solver, _ = solved(problem)
    ahead = ModesAhead(solver, None)
    ahead.start(1)
    deepest = solver.system(0, None)[1]
    assert len(ahead.modes(deepest)) == 1  # every layer by number: the same list
    assert ahead.modes(3) == {}  # 3 layers: a list of fewer nodes, not found ahead
    system, _ = solver.system(0, None)
    solver.multigrid(system).stale = True  # type: ignore[union-attr]
    solver._hierarchy(system, np.zeros((system.n_free, 3)), system.parameters(
        model_stiffness(problem, continuum_start(problem))))  # fmt: skip
    assert ahead.modes(None) == {}


def test_small_lists_are_left_to_the_prediction():
    """Lists with at most DENSE_UP_TO unknowns take dense modes: nothing to find ahead."""
    problem = box((4, 3, 3), "families+volume")
    solver, _ = solved(problem)
    ahead = ModesAhead(solver, None)
    ahead.start(1)
    assert ahead.modes(None) == {}


def test_a_calibration_finds_its_modes_beside_the_polish_once(monkeypatch):
    """The damping stage starts the modes after the polish's first round, on their own thread,
    and the prediction takes them: the modes are found once, and not on the stage's thread."""
    import threading

    from fpm.dynamics import eigen, modes_ahead
    from fpm.fitting.calibration import calibrate

    where: list[str] = []
    real = eigen.lowest_modes

    def counted(*args, **kwargs):
        where.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(modes_ahead, "lowest_modes", counted)
    monkeypatch.setattr("fpm.dynamics.modes.lowest_modes", counted)
    problem = box((11, 5, 5), "families+volume")
    calibrate(problem, chains=1)
    assert where == ["modes-ahead"]
