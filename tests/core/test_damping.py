"""Stage 2 of the calibration (:mod:`fpm.fitting.damping.search`): runs in pieces, the
critical-damping estimates against an exact mode, the linear response against the small-load limit
of the static equilibrium, early stopping, and the fastest d against a grid of d."""

from __future__ import annotations

import copy
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest

import fpm
from fpm.dynamics.equilibrium import StaticSolver, static_equilibrium
from fpm.dynamics.settle import force_tolerance
from fpm.dynamics.simulation import FpmModel
from fpm.dynamics.stability import auto_time_step
from fpm.dynamics.voigt import SETTLED
from fpm.fitting.damping import search as damping
from fpm.fitting.damping.choice import critical_damping
from fpm.fitting.damping.choice import fit_damping as find_damping
from fpm.fitting.damping.lockstep import CaseRun, _piece, _Runs, predicted_steps
from fpm.fitting.damping.margin import smallest_settling
from fpm.fitting.damping.search import _search, _unsure, fastest_damping
from fpm.fitting.damping.settings import DEFAULT
from fpm.fitting.damping.unsettled import (
    DampingError,
    Hopeless,
    hopeless,
    long_decay,
    what_would_work,
)
from fpm.model.forces import Stiffness
from fpm.model.stiffness import model_stiffness, spring_stiffness

CHUNK, MARGIN_PROBES, PREDICT_AFTER = DEFAULT.chunk, DEFAULT.margin_probes, DEFAULT.predict_after
SAMPLE, TRUST = DEFAULT.sample, DEFAULT.trust

K = 50.0
"""N/m."""


BAR: dict[str, Any] = {
    "name": "bar",
    "material": {"youngs_modulus": 5000.0, "poisson_ratio": 0.3, "density": 1000.0},
    "geometry": {
        "type": "box",
        "size": [0.02, 0.02, 0.04],
        "nodes": [3, 3, 5],
        "connectivity": "axis+face",
    },
    "fixed": [{"face": "z-"}],
    "load_cases": [
        {"forces": [{"at": [0.01, 0.01, 0.04], "vector": [0, 0, 0.05]}]},
        {"forces": [{"at": [0.01, 0.01, 0.04], "vector": [0.02, 0, 0.1]}]},
    ],
    "fpm": {"max_steps": 2000, "stiffness": "single", "dt": 1e-3},
}  # fmt: skip
"""A 3x3x5 axis+face lattice, bottom fixed, pulled at the top centre in two ways."""


@pytest.fixture(scope="module")
def bar() -> fpm.Problem:
    return fpm.load_problem(BAR)


def total_steps(problem: fpm.Problem, d: float) -> float:
    tolerance = force_tolerance(problem.spec)  # as fastest_damping runs without settle=
    runs = [fpm.simulate(problem, k=K, d=d, load_case=j, settle_tolerance=tolerance)
            for j in range(2)]  # fmt: skip
    return sum(r.steps for r in runs) if all(r.settled for r in runs) else math.inf


def test_a_run_in_pieces_is_the_run(bar: fpm.Problem):
    s = bar.spec.fpm
    model = FpmModel(bar)
    whole = model.run(1, k=K, d=0.1, depth=None, dt=s.dt, max_steps=900, settle_tolerance=1e-4)
    run = model.start(1, k=K, d=0.1, depth=None, dt=s.dt, settle_tolerance=1e-4)
    while not run.advance(7) and run.steps < 900:
        pass
    pieces = run.result()
    assert whole.settled and pieces.settled and pieces.steps == whole.steps
    assert np.array_equal(pieces.displacements, whole.displacements)


def test_critical_damping_of_an_exact_mode(bar: fpm.Problem):
    """For an eigenmode phi (K phi = w^2 M phi) held by loads w^2 M phi, the estimate is the
    mode's critical damping 2 w (phi^T M phi) / (phi^T phi) exactly."""
    solver = StaticSolver(bar)
    system, _ = solver.system(0, None)
    k = system.parameters(Stiffness(spring_stiffness(bar, K)))
    stiff = system.tangent(np.zeros((system.n_free, 3)), k).toarray()
    m = np.repeat(bar.solid.masses[system.free], 3)
    scale = 1 / np.sqrt(m)
    values, vectors = np.linalg.eigh(scale[:, None] * stiff * scale[None, :])
    w2, phi_free = values[0], scale * vectors[:, 0]
    phi = np.zeros((bar.n_nodes, 3))
    phi[system.free] = phi_free.reshape(-1, 3)
    shapes = np.stack([phi, phi])
    loads = w2 * bar.solid.masses[None, :, None] * shapes
    expected = 2 * math.sqrt(w2) * (phi_free @ (m * phi_free)) / (phi_free @ phi_free)
    assert critical_damping(bar, shapes, loads) == pytest.approx(expected, rel=1e-10)


def test_linear_response_is_the_small_load_limit(bar: fpm.Problem):
    """K^-1 f of the lattice at rest is what the static equilibrium tends to as f -> 0 (first
    order in f), by LU and by multigrid CG alike."""
    stiffness = spring_stiffness(bar, K)
    f = 1e-6 * bar.load_cases[1].dense(bar.n_nodes)
    lu = StaticSolver(bar).linear_response(1, stiffness, None, f)
    cg = StaticSolver(bar, amg_from=0).linear_response(1, stiffness, None, f)
    assert np.allclose(cg, lu, rtol=0, atol=1e-6 * np.abs(lu).max())
    spec = bar.spec.model_dump()
    spec["load_cases"][1]["forces"][0]["vector"] = [2e-8, 0, 1e-7]  # 1e-6 of the load
    tiny = static_equilibrium(fpm.load_problem(spec), k=K, load_case=1, tolerance=1e-10)
    assert np.allclose(lu, tiny.displacements, rtol=0, atol=1e-4 * np.abs(lu).max())


def test_a_d_that_cannot_win_stops_at_the_budget(bar: fpm.Problem):
    runs = _Runs(bar, spring_stiffness(bar, K), None, 1e-3)
    try:
        full, verdict = runs(0.4, [2000, 2000])
        assert verdict.outcome == "done" and all(r.result().settled for r in full)
        total = sum(r.steps for r in full)
        budget = total // 4
        stopped, verdict = runs(0.4, [2000, 2000], budget=budget)
        taken = sum(r.steps for r in stopped)
        assert verdict.outcome == "lost" and verdict.total >= budget
        # Decided by the first milestone past the budget (the two cases' steps up to it add up
        # to less than budget + 2 pieces), and no case ran more than a piece past it, however
        # the threads were scheduled: at most 4 pieces past the budget in all.
        assert taken < budget + 4 * CHUNK < total
        assert not all(r.finished for r in stopped)
    finally:
        runs.close()


def test_a_search_repeats_exactly_whatever_the_threads_do(bar: fpm.Problem):
    """Every decision is taken at milestones from each case's own state, so one thread or
    two give the same d, steps, d_min and tried list."""
    stiffness = spring_stiffness(bar, K)
    fits = []
    for threads in (1, 2):
        runs = _Runs(bar, stiffness, None, 1e-3)
        runs.pool.shutdown()
        runs.threads = threads
        runs.pool = ThreadPoolExecutor(threads)
        try:
            fits.append(_search(runs, (0.01, 8.0), (3.0, 6.0), None))
        finally:
            runs.close()
    one, two = fits
    assert (one.d, one.steps, one.d_min, one.tried) == (two.d, two.steps, two.d_min, two.tried)


@pytest.mark.parametrize("guesses", [(0.1, 0.2), (1.5, 1.5), (0.02, 0.02)])
def test_the_fastest_d_is_as_fast_as_a_grid_from_any_start(bar: fpm.Problem, guesses):
    """From good guesses and from guesses 10x too high or too low (the walk finds the way),
    the d found settles in at most 1.05x the fewest total steps of a 30-point log grid."""
    bounds = (0.01, 2.0)
    grid = min(total_steps(bar, d) for d in np.geomspace(*bounds, 30))
    fit = fastest_damping(bar, spring_stiffness(bar, K), None, bounds, guesses)
    assert fit.total_steps == total_steps(bar, fit.d)
    assert fit.total_steps <= 1.05 * grid
    assert bounds[0] <= fit.d_min <= fit.d
    assert total_steps(bar, fit.d_min) <= 2 * fit.total_steps


@pytest.mark.parametrize("d", [1.5, 3.0])
def test_the_decay_predicts_the_settle_steps(bar: fpm.Problem, d):
    """Overdamped runs (below d = 0.05 this bar diverges at its dt): past the transient, the
    residual's decay predicts the steps a run takes to settle within 15%."""
    runs = _Runs(bar, spring_stiffness(bar, K), None, 1e-3)
    try:
        run = runs.model.start(0, k=runs.stiffness, d=d, depth=None, dt=runs.dt,
                               settle_tolerance=force_tolerance(bar.spec))  # fmt: skip
        taken = _piece(run, PREDICT_AFTER)
        assert not run.finished, "the case must still run when the prediction is made"
        predicted = predicted_steps(run)
        taken += _piece(run, 20 * PREDICT_AFTER)
        assert run.state == SETTLED
        assert predicted == pytest.approx(run.steps, rel=0.15)
        assert taken == run.steps
    finally:
        runs.close()


class _Edge:
    """Stands in for _Runs in the margin search: every d >= ``edge`` settles within the caps;
    records the d probed and the d asked to run ahead."""

    def __init__(self, edge: float):
        self.edge = edge
        self.probed: list[float] = []
        self.ahead: list[float] = []

    def __call__(self, d: float, caps: list[int], *, estimate: bool = False) -> tuple[list, Any]:
        from fpm.fitting.damping.lockstep import Verdict

        self.probed.append(d)
        return [], Verdict("settles" if d >= self.edge else "failed")

    def prefetch(self, requests: list[Any]) -> None:
        """Nothing runs ahead here; the d asked for are recorded."""
        self.ahead += [r.d for r in requests]


@pytest.mark.parametrize("edge", [0.31, 0.52, 0.9])
def test_the_margin_uses_the_searchs_own_runs_and_finds_the_edge(edge):
    """The fastest d at 1.0; the search also dropped d = 0.4 and 0.7 on predictions (one
    within the caps or not, as the edge says) and settled 1.6. The margin lands within the
    walk's resolution (step / 2, log) above the edge, and never probes more d than a walk from
    1.0 that knows nothing of them: fewer once the tried d reach past its first step."""
    step = math.log(1.25)
    y_best = 0.0
    steps = {y_best: [100, 100], math.log(1.6): [150, 150]}
    forecast = {math.log(d): (150.0, 150.0) if d >= edge else (500.0, 500.0) for d in (0.4, 0.7)}
    with_runs, blind = _Edge(edge), _Edge(edge)
    d_min = math.exp(
        smallest_settling(with_runs, steps, forecast, y_best, math.log(0.01), 1000, step)
    )
    d_blind = math.exp(smallest_settling(blind, steps, {}, y_best, math.log(0.01), 1000, step))
    for found in (d_min, d_blind):
        assert edge <= found <= edge * math.exp(step / 2) * (1 + 1e-9)
    assert len(with_runs.probed) <= len(blind.probed)
    if edge < 0.7:  # the tried d reach further down than a walk's first step (1.25x)
        assert len(with_runs.probed) < len(blind.probed)
    assert all(d < 1.0 for d in with_runs.probed)  # the fastest d itself is never run again


@pytest.mark.parametrize("edge", [0.31, 0.52, 0.7, 0.8, 0.86, 0.95])
def test_the_margin_from_the_reduced_steps_edge_probes_it_first(edge):
    """The reduced steps' edge at 0.9 (the fastest d at 1.0, nothing tried below it): the edge
    first, asked to run ahead alone (where a worker is free); where it settles, 12% below it,
    and where that settles too, nothing more (MARGIN_PROBES); where it does not, no probe
    below it. d_min is the smallest d found that settles, and where one probe settles and
    the next below it does not (or the fastest d and a failing edge), they bracket the true
    ``edge``."""
    step = math.log(1.25)
    steps = {0.0: [100, 100]}
    runs = _Edge(edge)
    predicted = math.log(0.9)
    d_min = math.exp(smallest_settling(runs, steps, {}, 0.0, math.log(0.01), 1000, step, predicted))
    below = 0.9 / math.exp(step / 2)
    assert len(runs.probed) <= MARGIN_PROBES
    assert d_min >= edge and all(d < 1.0 for d in runs.probed)
    assert runs.probed[0] == pytest.approx(0.9)
    assert runs.ahead == pytest.approx([0.9])
    if edge <= 0.9:  # the edge settles: 12% below it next
        assert runs.probed[1:] == pytest.approx([below])
        assert d_min == pytest.approx(below if edge <= below else 0.9)
    else:  # the edge fails: nothing below it is run
        assert runs.probed == pytest.approx([0.9])
        assert d_min == pytest.approx(1.0)


class _Parabola:
    """A reduced step whose predicted steps are ``base * (1 + (log d - log d0)^2 / w^2)``."""

    def __init__(self, base: float, d0: float, width: float):
        self.base, self.d0, self.width = base, d0, width

    def steps(self, d: float, cap: int) -> float:
        return self.base * (1 + (math.log(d / self.d0) / self.width) ** 2)


def test_a_confirming_run_is_skipped_only_beyond_twice_the_reduced_steps_error():
    """Predicted 1,000 steps at the fastest d and 1,100 at a side (10% more): the side is
    ruled out while the runs at the fastest d measured within 5% of the prediction (10% >
    TRUST x 5%), confirmed once they measured 6% or more off, either way, or did not settle."""
    assert TRUST == 2.0
    side = math.log(1.04)
    width = side / math.sqrt(0.1)  # 10% more steps at a side
    models = [_Parabola(600.0, 1.0, width), _Parabola(400.0, 1.0, width)]
    assert models[0].steps(1.04, 0) + models[1].steps(1.04, 0) == pytest.approx(1100.0)
    for measured, needed in [
        ([600, 400], False),
        ([630, 420], False),  # 1,050: 4.8% off
        ([640, 420], True),  # 1,060: 5.7% off
        ([560, 380], True),  # 940: 6.4% off, under the prediction
        (None, True),
    ]:
        for y in (side, -side):
            assert _unsure(models, measured, y, 0.0) is needed, (measured, y)


# ------------------------------------------------------------------ a case that cannot settle


def slow_bar(dt: float, max_steps: int | str) -> fpm.Problem:
    """The bar at a time step far below its stability limit: its runs need tens of thousands
    of steps (about 65,000 and 77,000 at 2e-6 s, measured with max_steps 'auto')."""
    spec = copy.deepcopy(BAR)
    spec["load_cases"][0]["name"], spec["load_cases"][1]["name"] = "pull", "pull sideways"
    spec["fpm"].update(dt=dt, max_steps=max_steps)
    return fpm.load_problem(spec)


def search_runs(problem: fpm.Problem, monkeypatch: pytest.MonkeyPatch) -> tuple[Any, list[Any]]:
    """find_damping at K with every d's runs recorded: (its answer or its DampingError, [d])."""
    tried: list[float] = []
    separate, lockstep = _Runs.separate, _Runs._lockstep

    def seen_separate(self: _Runs, d: float, *args: Any, **kwargs: Any) -> Any:
        tried.append(d)
        return separate(self, d, *args, **kwargs)

    def seen_lockstep(self: _Runs, request: Any, *args: Any) -> Any:
        tried.append(request.d)
        return lockstep(self, request, *args)

    monkeypatch.setattr(_Runs, "separate", seen_separate)
    monkeypatch.setattr(_Runs, "_lockstep", seen_lockstep)
    stiffness = model_stiffness(problem, [K])
    solver = StaticSolver(problem)
    static = np.stack([solver.solve(j, stiffness, None).displacements for j in range(2)])
    dt = float(problem.spec.fpm.dt)
    try:
        answer: Any = find_damping(problem, solver, stiffness, 9, static, dt)[0]
    except DampingError as e:
        answer = e
    return answer, tried


def test_a_case_that_cannot_settle_within_the_budget_stops_the_search_at_once(
    monkeypatch: pytest.MonkeyPatch,
):
    """At max_steps 5,000 the runs of the predicted d are still moving at their cap, their
    distance from equilibrium growing over the run's second half: the search ends there,
    naming the cases and their strain, without trying another d or a probe run."""
    error, tried = search_runs(slow_bar(2e-6, 5000), monkeypatch)
    assert isinstance(error, DampingError)
    message = str(error)
    for name in ("pull", "pull sideways"):
        assert f"load case '{name}' cannot settle within the step budget" in message
    assert "(fpm.max_steps = 5,000)" in message and "strains a spring by" in message
    assert len(tried) == 1  # the predicted d only


def test_a_cap_short_by_less_than_the_slack_searches_on_as_before(monkeypatch: pytest.MonkeyPatch):
    """At dt 2e-5 and max_steps 800 the decay predicts 2,900 and 3,900 steps, under
    HOPELESS times the cap: the search tries the other d and explains as before."""
    error, tried = search_runs(slow_bar(2e-5, 800), monkeypatch)
    assert isinstance(error, DampingError)
    assert "cannot settle within the step budget" not in str(error)
    assert str(error).startswith("no d in") and len(tried) > 3


def test_the_settling_bar_is_found_as_before_with_auto_steps(monkeypatch: pytest.MonkeyPatch):
    """Under 'auto' the modes predict the slow bar's steps and its cap holds them: no stop."""
    fit, _ = search_runs(slow_bar(2e-6, "auto"), monkeypatch)
    assert not isinstance(fit, DampingError)
    assert min(fit.steps) > 10 * CHUNK and fit.max_steps > max(fit.steps)


def decaying(steps: int, rate: float, settle: float, rising: bool = False) -> CaseRun:
    """A run stopped at ``steps`` whose residual falls as exp(-rate n) (rises, ``rising``),
    sampled every SAMPLE steps."""
    sign = 1 if rising else -1
    history = [(n, math.exp(sign * rate * n)) for n in range(SAMPLE, steps + 1, SAMPLE)]
    return CaseRun(steps=steps, state=0, settle_force=settle, history=history)


def test_the_long_decay_reads_the_whole_run():
    # exp(-n / 1000) reaches exp(-10) at 10,000 steps; read from the envelope, which starts a
    # sample into each quarter, the estimate is late by up to a quarter of the run
    assert 10_000 <= long_decay(decaying(4000, 1e-3, math.exp(-10))) <= 11_000
    assert long_decay(decaying(4000, 1e-3, math.exp(-10), rising=True)) == math.inf
    assert long_decay(decaying(1000, 1e-3, math.exp(-10))) == 1000  # too short to read


def test_no_probe_repeats_what_the_searchs_own_runs_said(bar: fpm.Problem, monkeypatch):
    """With the cap at the schema's 10^6 and dt already at the stability estimate's half, the
    explanation runs nothing more (such a probe would repeat the search's runs); below, it
    probes once at the smaller dt."""
    stiffness = spring_stiffness(bar, K)
    dt = auto_time_step(bar, stiffness)
    probes: list[float] = []
    call = _Runs.__call__

    def probe(self: _Runs, d: float, *args: Any, **kwargs: Any) -> Any:
        probes.append(self.dt)
        return call(self, d, *args, **kwargs)

    monkeypatch.setattr(_Runs, "__call__", probe)
    runs, coarse = _Runs(bar, stiffness, None, dt), _Runs(bar, stiffness, None, 2 * dt)
    try:
        said = what_would_work(runs, 0.4, 1_000_000)
        assert "no d settles within 1000000 steps" in said and probes == []
        said = what_would_work(coarse, 0.4, 2000)
        assert probes == [dt] and "settles within" in said
    finally:
        runs.close()
        coarse.close()


def test_a_case_whose_settling_recedes_as_its_cap_grows_is_named():
    """The predicted d's case given the cap its decay asked for (30,000 steps, predicted at
    13,812) and still moving there is creeping: named at once; one that settled, or whose cap
    did not reach what was asked, is not."""
    problem = slow_bar(2e-6, "auto")
    earlier = [(13_812, 30_000.0, True), (1_803, 1_803.0, False)]
    settled = (1_803, 1_803.0, False)
    with pytest.raises(DampingError, match="load case 'pull' does not settle: .* creeps"):
        hopeless(problem, 0.02, [(55_000, 55_000.0, True), settled], 10**6, True, [], earlier)
    hopeless(problem, 0.02, [(41_000, 41_000.0, False), settled], 10**6, True, [], earlier)
    hopeless(problem, 0.02, [(20_000, 90_000.0, True), settled], 10**6, True, [], earlier)
    hopeless(problem, 0.02, [(55_000, 90_000.0, True), settled], 10**6, True, [], None)


def test_a_hopeless_case_is_not_retried_under_a_larger_cap(bar: fpm.Problem, monkeypatch):
    """Under fpm.max_steps 'auto' a failed search is retried with a larger cap; one that found a
    case that cannot settle whatever its cap (Hopeless) is not."""
    calls: list[int] = []
    error: list[type[DampingError]] = []

    def search(runs: _Runs, *args: Any, **kwargs: Any) -> Any:
        calls.append(runs.max_steps)
        raise error[0]("nothing settles")

    monkeypatch.setattr(damping, "_search", search)
    for kind, tries in ((Hopeless, 1), (DampingError, 3)):
        calls.clear()
        error[:] = [kind]
        with pytest.raises(DampingError):
            fastest_damping(bar, spring_stiffness(bar, K), None, (0.01, 1.0), (0.1, 0.1),
                            max_steps=1000, auto=True)  # fmt: skip
        assert len(calls) == tries
