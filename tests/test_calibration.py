"""Calibration: the annealer's rules, reproducibility, and recovery of a known stiffness."""

from __future__ import annotations

import math

import numpy as np
import pytest

import fpm
from fpm.annealing import AnnealingError, Schedule, State, anneal, metropolis
from fpm.calibration import calibrate, finalize, run_chain
from fpm.cost import CostFunction

K_TRUE = 50.0


def small_spec(**annealing) -> dict:
    """A 3x3x5 axis lattice, bottom fixed, pulled up at the top centre; a short schedule."""
    return {
        "name": "small bar",
        "material": {"youngs_modulus": 5000.0, "poisson_ratio": 0.3, "density": 1000.0},
        "geometry": {"type": "box", "size": [0.02, 0.02, 0.04], "nodes": [3, 3, 5],
                     "connectivity": "axis+face"},
        "fixed": [{"face": "z-"}],
        "load_cases": [
            {"forces": [{"at": [0.01, 0.01, 0.04], "vector": [0, 0, 0.05]}]},
            {"forces": [{"at": [0.01, 0.01, 0.04], "vector": [0.02, 0, 0.1]}]},
        ],
        "fpm": {"depth": 10},
        "annealing": {"seed": 3, "chains": 2, "t_initial": 0.05, "t_final": 1e-3, "beta": 15.0,
                      **annealing},
    }  # fmt: skip


@pytest.fixture(scope="module")
def small():
    """The small problem and its own FPM reference at K_TRUE (so the best k is known)."""
    problem = fpm.load_problem(small_spec())
    ref = np.stack(
        [
            fpm.simulate(problem, k=K_TRUE, d=0.2, load_case=j, max_steps=50000,
                         settle_tolerance=1e-10).displacements
            for j in range(len(problem.load_cases))
        ]
    )  # fmt: skip
    return problem, ref


def test_schedule_follows_lundy_mees_and_stops_below_t_final():
    s = Schedule(t_initial=0.1, t_final=1e-3, beta=7.0)
    temps = [s.temperature(n) for n in range(s.moves)]
    for t0, t1 in zip(temps, temps[1:], strict=False):
        assert t1 == pytest.approx(t0 / (1 + 7.0 * t0), rel=1e-12)
    # the last move is judged at or above t_final, the next temperature would be below it
    assert temps[-1] >= 1e-3 > s.temperature(s.moves)
    assert s.moves == math.floor((1 / 1e-3 - 1 / 0.1) / 7.0) + 1


def test_metropolis_acceptance_rate_matches_boltzmann():
    rng = np.random.default_rng(0)
    n = 200_000
    for delta, t in ((0.01, 0.01), (0.03, 0.01), (0.002, 0.004)):
        rate = np.mean([metropolis(delta, t, u) for u in rng.random(n)])
        expected = math.exp(-delta / t)
        assert abs(rate - expected) < 4 * math.sqrt(expected * (1 - expected) / n)
    assert all(metropolis(-1.0, 1e-9, u) for u in (0.0, 0.5, 0.999))


def quadratic(calls: list):
    def objective(x):
        calls.append(list(x))
        return State(list(x), (math.log(x[0] / 3.0)) ** 2 + (math.log(x[1] / 0.5)) ** 2)

    return objective


def test_anneal_counts_every_evaluation_and_is_repeatable():
    calls: list = []
    sched = Schedule(0.5, 1e-4, 20.0)
    r1 = anneal(quadratic(calls), np.array([0.1, 0.01]), np.array([100, 10]), sched,
                np.random.default_rng(1), c_max=100)  # fmt: skip
    assert r1.evaluations == len(calls)
    assert len(r1.history) == sched.moves
    r2 = anneal(quadratic([]), np.array([0.1, 0.01]), np.array([100, 10]), sched,
                np.random.default_rng(1), c_max=100)  # fmt: skip
    assert r1.best.x == r2.best.x and r1.history == r2.history
    assert r1.best.x[0] == pytest.approx(3.0, rel=0.05)
    assert r1.best.x[1] == pytest.approx(0.5, rel=0.05)


def test_divergent_and_over_c_max_candidates_are_never_accepted():
    def objective(x):
        # "diverges" (inf) right of k = 5, costs above c_max between 2 and 5
        if x[0] > 5:
            return State(list(x), math.inf)
        return State(list(x), 10.0 if x[0] > 2 else abs(math.log(x[0])))

    r = anneal(objective, np.array([0.1, 0.1]), np.array([50.0, 1.0]), Schedule(1.0, 1e-3, 10.0),
               np.random.default_rng(5), c_max=5.0)  # fmt: skip
    assert all(c <= 5.0 for c in r.history)
    assert r.best.x[0] <= 2


def test_no_acceptable_start_is_a_clear_error():
    with pytest.raises(AnnealingError, match="diverged"):
        anneal(lambda x: State(list(x), math.inf), np.array([1.0, 1.0]), np.array([2.0, 2.0]),
               Schedule(1.0, 0.1, 1.0), np.random.default_rng(0), c_max=1.0)  # fmt: skip


def test_checkpoint_resume_gives_the_uninterrupted_chain():
    saved = []
    sched = Schedule(0.5, 1e-3, 20.0)
    args = (np.array([0.1, 0.01]), np.array([100, 10]), sched)
    full = anneal(quadratic([]), *args, np.random.default_rng(9), c_max=100,
                  checkpoint=saved.append, checkpoint_every=7)  # fmt: skip
    snap = saved[2]
    calls: list = []
    resumed = anneal(quadratic(calls), *args, np.random.default_rng(123), c_max=100, resume=snap)
    assert resumed.best.x == full.best.x and resumed.history == full.history
    assert len(calls) == sched.moves - snap["move"]  # only the remaining moves were evaluated


def test_cost_is_eq2_and_zero_at_the_reference(small):
    problem, ref = small
    cost = CostFunction(problem, ref, 10)
    ev = cost(K_TRUE, 0.2)
    # not exactly zero: the run stops once the unbalanced force is below the settle tolerance
    assert ev.settled and ev.cost < 2e-3 * cost.reference_cost
    # an FPM that does not move costs the summed reference displacement
    assert cost.reference_cost == pytest.approx(np.linalg.norm(ref, axis=2).sum())
    assert cost.evaluations == 1


def test_chain_recovers_the_known_stiffness_and_repeats_exactly(small):
    problem, ref = small
    a = run_chain(problem, ref, 0)
    b = run_chain(problem, ref, 0)
    assert (a.k, a.d, a.cost, a.history) == (b.k, b.d, b.cost, b.history)
    assert a.k == pytest.approx(K_TRUE, rel=0.01)
    other = run_chain(problem, ref, 1)
    assert other.history != a.history  # chains are independent draws


def test_calibrate_reports_counts_and_picks_the_fastest_settling_near_best(small):
    problem, ref = small
    seen = []
    result = calibrate(problem, reference=ref, progress=seen.append)
    assert result.k == pytest.approx(K_TRUE, rel=0.01)
    assert result.settled and result.depth == 10
    assert result.evaluations == sum(c["evaluations"] for c in result.chains)
    assert {s.get("phase") for s in seen} == {"annealing", "finalize"}
    assert len(result.discrepancy) == 2 and max(result.discrepancy) < 0.5
    # same seed, same answer, whether chains run on threads or one after the other
    again = calibrate(problem, reference=ref, threads=1)
    assert (again.k, again.d, again.settle_steps) == (result.k, result.d, result.settle_steps)


def test_finalize_prefers_the_fastest_settling_state_within_a_tenth_of_a_percent(small):
    problem, ref = small
    chain = run_chain(problem, ref, 0)
    best = min(chain.near_best, key=lambda s: s["cost"])
    fast = dict(best, d=best["d"], cost=best["cost"] * 1.0009, steps=[1, 1])
    slow_but_cheapest = dict(best, steps=[10_000, 10_000])
    too_far = dict(best, cost=best["cost"] * 1.002, steps=[0, 0])
    chain.near_best = [slow_but_cheapest, fast, too_far]
    chain.cost = best["cost"]
    result = finalize(problem, ref, [chain])
    assert (result.k, result.d) == (fast["k"], fast["d"])


def test_auto_depth_is_the_smallest_depth_close_to_full_depth(small):
    problem = fpm.load_problem(small_spec() | {"fpm": {"depth": "auto"}})
    _, ref = small
    result = calibrate(problem, reference=ref, chains=1)
    cost = CostFunction(problem, ref, None)
    full = [cost.displacements(result.k, result.d, j, None).displacements for j in range(2)]

    def worst(depth):
        return max(
            np.linalg.norm(cost.displacements(result.k, result.d, j, depth).displacements - full[j],
                           axis=1).mean()
            for j in range(2)
        )  # fmt: skip

    assert worst(result.depth) <= 0.01 * problem.h
    if result.depth > 0:
        assert worst(result.depth - 1) > 0.01 * problem.h


def test_cli_calibrate_prints_a_table_and_draws_the_plot(tmp_path):
    import json
    import subprocess
    import sys

    spec = tmp_path / "small.json"
    spec.write_text(json.dumps(small_spec(t_final=5e-3)))
    png = tmp_path / "fit.png"
    run = subprocess.run(
        [sys.executable, "-m", "fpm.cli", "calibrate", str(spec), "--plot", str(png)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "discrepancy % of h" in run.stdout and "settled: yes" in run.stdout
    assert "annealing [" in run.stderr  # the progress bar
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_fem_writes_the_reference(tmp_path):
    import json
    import subprocess
    import sys

    spec = tmp_path / "small.json"
    spec.write_text(json.dumps(small_spec()))
    out = tmp_path / "fem.json"
    run = subprocess.run(
        [sys.executable, "-m", "fpm.cli", "fem", str(spec), "-o", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    data = json.loads(out.read_text())
    expected = fpm.solve_fem(fpm.load_problem(small_spec())).displacements
    assert np.allclose(np.asarray(data["displacements"]), expected)


def test_spec_and_schedule_agree_on_the_number_of_moves():
    for t0, tf, beta in ((0.05, 2e-4, 33.0), (0.1, 1e-3, 7.0), (0.05, 1e-3, 15.0), (1.0, 0.5, 1.0)):
        spec = fpm.ProblemSpec.model_validate(
            small_spec(t_initial=t0, t_final=tf, beta=beta)
        ).annealing
        assert spec.moves == Schedule(t0, tf, beta).moves
