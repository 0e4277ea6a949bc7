"""The FPM (paper Sec. 3, Eq. 1) against mathematics: analytic equilibria of springs, chains, an
axis-lattice bar and a hanging chain; Newton's third law; invariance of the equilibrium under
scaling; and the run's bookkeeping (divergence, repeatability, what does and does not move).

Every equilibrium check allows what the settle criterion allows: a run stops once every free
node's unbalanced force is below ``settle_tolerance * F_max``; a residual r per node shifts a
chain of n springs by at most n(n+1)/2 * r / k at its tip.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers_fpm import box_spec, chain_spec, spring_forces

import fpm
from fpm.dynamics.simulation import fpm_model

ROOT = Path(__file__).resolve().parents[2]
TIGHT = {"dt": 1e-3, "settle_tolerance": 1e-10, "max_steps": 100_000}


def bar_spec(cells: int, f: float, scale=(1.0, 1.0, 1.0), h: float = 0.01) -> dict:
    """A 2 x 2 x (cells + 1) `axis` lattice, face z- fixed, +z force f on each of the 4 end
    nodes: four parallel chains of ``cells`` springs, tied by unstretched lateral springs."""
    top = cells * h
    forces = [{"at": [i * h, j * h, top], "vector": [0, 0, f]} for i in (0, 1) for j in (0, 1)]
    return box_spec(
        (2, 2, cells + 1),
        h,
        connectivity="axis",
        forces=forces,
        fpm_settings={**TIGHT, "stiffness_scale": list(scale)},
    )


def block_problem(force_scale: float = 1.0) -> fpm.Problem:
    """A 3 x 3 x 4 `full` lattice, face z- fixed, an oblique force on one top corner."""
    spec = box_spec(
        (3, 3, 4),
        0.01,
        connectivity="full",
        forces=[{"at": [0, 0, 0.03], "vector": list(force_scale * np.array([3e-3, -2e-3, 1e-2]))}],
        fpm_settings={"dt": 1e-3, "settle_tolerance": 1e-9, "max_steps": 20_000},
    )
    return fpm.load_problem(spec)


# --- analytic equilibria ------------------------------------------------------------------


def test_single_spring_settles_at_f_over_k():
    f, k = 0.01, 10.0
    problem = fpm.load_problem(
        chain_spec(1, 0.01, (1, 0, 0), tip_force=[f, 0, 0], fpm_settings=TIGHT)
    )
    result = fpm.simulate(problem, k=k, d=0.6)  # about critical: 2 sqrt(k m) = 0.63
    assert result.settled and not result.diverged
    assert result.displacements[1, 0] == pytest.approx(f / k, rel=1e-8)
    assert np.all(result.displacements[1, 1:] == 0)  # no force across the spring, no motion
    assert np.all(result.displacements[0] == 0)
    assert result.residual < 1e-10 * f


@pytest.mark.parametrize("n", [2, 5, 9])
def test_chain_in_series_stretches_each_spring_by_f_over_k(n: int):
    """n springs in series along a skew line, the tip pulled along the line: every spring
    carries F, so each stretches F/k and the tip moves n F/k, along the line."""
    f, k, length = 0.01, 10.0, 0.01
    e = np.array([1.0, 2.0, 2.0]) / 3.0
    problem = fpm.load_problem(
        chain_spec(n, length, tuple(e), tip_force=list(f * e), fpm_settings=TIGHT)
    )
    result = fpm.simulate(problem, k=k, d=0.2)
    assert result.settled and result.perturbed == n
    x = problem.nodes + result.displacements
    stretched = np.linalg.norm(np.diff(x, axis=0), axis=1) - length
    assert stretched == pytest.approx(np.full(n, f / k), rel=1e-7)
    tip = result.displacements[n]
    assert tip == pytest.approx(n * f / k * e, rel=1e-7, abs=1e-15)


def test_axis_lattice_bar_stretches_like_four_chains():
    """Node at level j moves j f / k along z; the lateral springs stay unstretched."""
    cells, f, k, h = 6, 0.01, 10.0, 0.01
    problem = fpm.load_problem(bar_spec(cells, f))
    result = fpm.simulate(problem, k=k, d=0.02)
    assert result.settled
    u = result.displacements.reshape(cells + 1, 4, 3)  # [level, node in level, xyz]
    expected = np.arange(cells + 1) * f / k
    assert u[..., 2] == pytest.approx(np.repeat(expected[:, None], 4, axis=1), rel=1e-6, abs=1e-12)
    assert np.abs(u[..., :2]).max() < 1e-9 * h
    x = problem.nodes + result.displacements
    s = problem.solid.springs
    lateral = problem.nodes[s[:, 0], 2] == problem.nodes[s[:, 1], 2]
    assert lateral.sum() == 4 * (cells + 1)
    lengths = np.linalg.norm(x[s[:, 1]] - x[s[:, 0]], axis=1)
    assert lengths[lateral] == pytest.approx(np.full(lateral.sum(), h), rel=1e-9)


@pytest.mark.parametrize(("scale", "factor"), [((1, 1, 2), 2.0), ((3, 5, 1), 1.0)])
def test_stiffness_scale_along_the_bar(scale, factor):
    """k_e = k (sx ex^2 + sy ey^2 + sz ez^2): sz = 2 halves the stretch of the longitudinal
    chains; sx, sy only stiffen the lateral springs, which carry no force here. (dt = 0.4 ms:
    five times stiffer springs need a shorter explicit step.)"""
    cells, f, k = 6, 0.01, 10.0
    problem = fpm.load_problem(bar_spec(cells, f, scale=scale))
    result = fpm.simulate(problem, k=k, d=0.02, dt=4e-4)
    assert result.settled
    tip = result.displacements.reshape(cells + 1, 4, 3)[-1, :, 2]
    assert tip == pytest.approx(np.full(4, cells * f / (factor * k)), rel=1e-6)


def test_stiffness_scale_of_an_oblique_spring():
    """One spring along e = (1, 0, 1)/sqrt2 with scale (1, 1, 3): k_e = k (1/2 + 3/2) = 2k."""
    f, k = 0.01, 10.0
    e = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    spec = chain_spec(1, 0.01, tuple(e), tip_force=list(f * e), fpm_settings=TIGHT)
    spec["fpm"]["stiffness_scale"] = [1.0, 1.0, 3.0]
    result = fpm.simulate(fpm.load_problem(spec), k=k, d=0.8)
    assert result.settled
    assert result.displacements[1] == pytest.approx(f / (2 * k) * e, rel=1e-7, abs=1e-15)


def test_hanging_chain_sags_by_the_weight_below_each_spring():
    """A chain hanging from node 0 under gravity, a small weight P at the tip: spring i (from
    node i-1 to node i) carries P + (n - i + 1) m g, so node j sinks by the sum of those / k
    over i <= j. (Every load case needs a force: P is that force.)"""
    n, m, g, k, p = 5, 0.01, 9.81, 200.0, 0.02
    spec = chain_spec(n, 0.01, (0, 0, -1), tip_force=[0, 0, -p], mass=m, fpm_settings=TIGHT)
    spec["fpm"]["gravity"] = [0.0, 0.0, -g]
    result = fpm.simulate(fpm.load_problem(spec), k=k, d=0.3)
    assert result.settled
    tension = p + (n - np.arange(1, n + 1) + 1) * m * g  # spring i = 1..n
    sag = np.concatenate([[0.0], np.cumsum(tension / k)])
    assert -result.displacements[:, 2] == pytest.approx(sag, rel=1e-7)
    assert np.all(result.displacements[:, :2] == 0)


# --- equilibrium and Newton's third law ---------------------------------------------------


def test_spring_forces_cancel_and_balance_the_applied_forces():
    k = 10.0
    problem = block_problem()
    tol = 1e-5  # the force criterion, named
    result = fpm.simulate(problem, k=k, d=0.1, settle_tolerance=tol)
    assert result.settled
    applied = problem.load_cases[0].dense(problem.n_nodes)
    f_max = np.linalg.norm(applied, axis=1).max()
    x = problem.nodes + result.displacements
    fs = spring_forces(x, problem.solid.springs, problem.rest_lengths, k)
    # Third law: the internal forces sum to zero over all nodes, to round-off.
    assert np.abs(fs.sum(axis=0)).max() < 1e-12 * np.abs(fs).max()
    # Each free node: spring force balances the applied force within the settle tolerance
    # (x2: the sweep measured each node before its own last move).
    free = ~problem.fixed
    unbalanced = np.linalg.norm(applied[free] + fs[free], axis=1)
    assert unbalanced.max() < 2 * tol * f_max
    # Hence the springs pull on the supports with the whole load.
    on_supports = fs[problem.fixed].sum(axis=0)
    assert on_supports == pytest.approx(applied.sum(axis=0), abs=problem.n_nodes * tol * f_max)
    # Not trivially: the springs are loaded far beyond the residual.
    assert np.abs(fs[free]).max() > 1e4 * tol * f_max


def test_scaling_force_and_stiffness_together_keeps_the_displacements():
    """F -> 10 F, k -> 10 k leaves the equilibrium equations F + sum k (...) = 0 unchanged, so
    the settled displacements agree. The runs themselves differ (same dt, d and masses, ten
    times stiffer springs: other dynamics and step counts; dt = 0.3 ms keeps the stiffer run
    inside the explicit limit), and each stops with a residual up to settle_tolerance * F_max,
    i.e. 1e-9 relative to its own load; mapped through the lattice's compliance that is about
    1e-8 of the largest displacement here (measured), so 1e-6 leaves a wide margin."""
    k, dt = 10.0, 3e-4
    base = fpm.simulate(block_problem(), k=k, d=0.1, dt=dt)
    scaled = fpm.simulate(block_problem(10.0), k=10 * k, d=0.1, dt=dt)
    assert base.settled and scaled.settled
    assert base.steps != scaled.steps  # the dynamics differ ...
    u = np.abs(base.displacements).max()
    assert scaled.displacements == pytest.approx(base.displacements, abs=1e-6 * u)  # ... not so


# --- bookkeeping: divergence, repeatability, what moves ------------------------------------


def test_too_little_damping_at_a_large_dt_diverges():
    """Single spring, omega = sqrt(k/m) = 31.6 /s: dt = 0.1 puts omega dt = 3.2 past the explicit
    limit 2, and light damping cannot save it; heavy damping (taken implicitly) can."""
    spec = chain_spec(1, 0.01, (1, 0, 0), tip_force=[0.01, 0, 0], fpm_settings=TIGHT)
    problem = fpm.load_problem(spec)
    for d in (0.0, 0.01):
        result = fpm.simulate(problem, k=10.0, d=d, dt=0.1, max_steps=1000)
        assert result.diverged and not result.settled
        assert result.steps < 1000  # stopped as soon as it left the solid's size
    heavy = fpm.simulate(problem, k=10.0, d=100.0, dt=0.1, max_steps=10_000)
    assert heavy.settled and not heavy.diverged
    assert heavy.displacements[1, 0] == pytest.approx(1e-3, rel=1e-6)


def test_paper_lattice_diverges_undamped_at_the_fig7_step():
    problem = fpm.load_problem(ROOT / "examples" / "paper-material-a.json")
    result = fpm.simulate(problem, k=38.6, d=0.0, dt=0.05)
    assert result.diverged and not result.settled
    assert result.steps < problem.spec.fpm.max_steps
    json.dumps(result.to_dict(), allow_nan=False)  # still a valid JSON answer


def test_runs_are_bit_for_bit_repeatable():
    first = fpm.simulate(block_problem(), k=10.0, d=0.1, max_steps=300)
    problem = block_problem()
    for _ in range(2):
        again = fpm.simulate(problem, k=10.0, d=0.1, max_steps=300)
        assert np.array_equal(again.displacements, first.displacements)
        assert (again.steps, again.residual) == (first.steps, first.residual)


def test_only_the_perturbed_list_moves_and_fixed_nodes_never_do():
    problem = fpm.load_problem(
        box_spec(
            (6, 6, 6),
            0.01,
            connectivity="full",
            fixed=[{"face": "z-"}, {"face": "x-"}],
            forces=[{"at": [0.03, 0.02, 0.05], "vector": [0.01, 0.0, 0.02]}],
        )
    )
    for depth in (0, 1, 2, None):
        result = fpm.simulate(
            problem, k=10.0, d=0.1, depth=depth, settle_tolerance=0, max_steps=200
        )
        plist = fpm_model(problem).perturbed_list(0, depth)
        listed = np.zeros(problem.n_nodes, dtype=bool)
        listed[plist.order] = True
        moved = np.any(result.displacements != 0, axis=1)
        assert not moved[~listed].any()
        assert not moved[problem.fixed].any()
        assert moved[plist.layer(plist.layers)].all()  # the outermost layer did move
        assert result.perturbed == listed.sum()


def test_a_list_layout_is_the_same_lattice_renumbered():
    """The layout lists the perturbed list's nodes first in visiting order, is a permutation,
    and every list node keeps exactly its springs (neighbour, rest length, spring) renamed."""
    problem = block_problem()
    model = fpm_model(problem)
    a = model.adjacency
    for depth in (0, 1, None):
        plist = model.perturbed_list(0, depth)
        layout = model.layout(plist)
        m = len(plist.order)
        assert np.array_equal(layout.nodes[:m], plist.order)
        assert np.array_equal(np.sort(layout.nodes), np.arange(problem.n_nodes))
        assert np.array_equal(layout.local[layout.nodes], np.arange(problem.n_nodes))
        assert np.array_equal(layout.order, np.arange(m))
        for i, node in enumerate(plist.order):
            rows = layout.rows
            mine = slice(rows.ptr[i], rows.ptr[i + 1])
            theirs = slice(a.ptr[node], a.ptr[node + 1])
            assert np.array_equal(layout.nodes[rows.neighbour[mine]], a.neighbour[theirs])
            assert np.array_equal(rows.rest_length[mine], a.rest_length[theirs])
            assert np.array_equal(rows.spring[mine], a.spring[theirs])


def test_the_layout_changes_no_bit_of_a_run():
    """A run on the list's own numbering equals, bit for bit, the kernel run on the solid's
    numbering (same arithmetic in the same order), with the volume term and per-spring k."""
    from fpm.dynamics.voigt import run_steps
    from fpm.model.stiffness import continuum_start, model_stiffness

    spec = box_spec(
        (4, 5, 6), 0.01, connectivity="full",
        forces=[{"at": [0.01, 0.02, 0.05], "vector": [0.05, -0.02, 0.1]}],
        fpm_settings={"stiffness": "families+volume", "dt": 2e-4},
    )  # fmt: skip
    problem = fpm.load_problem(spec)
    stiffness = model_stiffness(problem, continuum_start(problem))
    result = fpm.simulate(problem, k=continuum_start(problem), d=0.05, settle_tolerance=0,
                          max_steps=400)  # fmt: skip
    model = fpm_model(problem)
    a, plist = model.adjacency, model.perturbed_list(0, None)
    cells, which = model.active_cells(plist)
    x, v = problem.nodes.copy(), np.zeros_like(problem.nodes)
    taken, *_ = run_steps(
        plist.order, a.ptr, a.neighbour, a.rest_length, stiffness.springs[a.spring],
        problem.nodes, x, v, problem.load_cases[0].dense(problem.n_nodes), problem.solid.masses,
        1.0, 0.05, 2e-4, 400, 0.0, 0.0, problem.size, cells.corners, cells.rest, cells.volume,
        np.ascontiguousarray(stiffness.volume[which]), np.zeros_like(x), np.zeros((0, 3)), 0.0, 0.0,
    )  # fmt: skip
    assert taken == result.steps == 400
    assert np.array_equal(x - problem.nodes, result.displacements)


def test_zero_settle_tolerance_never_settles():
    problem = fpm.load_problem(chain_spec(1, 0.01, (1, 0, 0), tip_force=[0.01, 0, 0]))
    result = fpm.simulate(problem, k=10.0, d=0.6, settle_tolerance=0, max_steps=5000)
    assert result.steps == 5000
    assert not result.settled and not result.diverged
    # ... although it reached the equilibrium long before.
    assert result.displacements[1, 0] == pytest.approx(1e-3, rel=1e-12)


def test_simulate_refuses_bad_arguments():
    problem = fpm.load_problem(chain_spec(1, 0.01, (1, 0, 0), tip_force=[0.01, 0, 0]))
    for kwargs in (
        {"k": 0.0, "d": 1.0},
        {"k": 1.0, "d": -1.0},
        {"k": 1.0, "d": 1.0, "load_case": 1},
    ):
        with pytest.raises(ValueError):
            fpm.simulate(problem, **kwargs)


@pytest.mark.parametrize(
    "override",
    [{"depth": -1}, {"dt": 0.0}, {"dt": -1e-3}, {"max_steps": 0}, {"settle_tolerance": -1.0}],
    ids=["depth", "dt-zero", "dt-negative", "max-steps", "settle-tolerance"],
)
def test_simulate_refuses_overrides_the_schema_would_refuse(override):
    problem = fpm.load_problem(chain_spec(1, 0.01, (1, 0, 0), tip_force=[0.01, 0, 0]))
    with pytest.raises(ValueError):
        fpm.simulate(problem, k=10.0, d=0.6, **override)


# --- the command line ---------------------------------------------------------------------


def test_cli_simulate_prints_the_result_as_json():
    script = Path(sys.executable).with_name("fpmcal")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "fpmcal.cli"]
    spec = ROOT / "examples" / "paper-material-a.json"
    run = subprocess.run(
        [*command, "simulate", str(spec), "--k", "38.6", "--d", "0.3"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert {"nodes", "displacements", "steps", "settled", "diverged", "perturbed"} <= out.keys()
    u = np.asarray(out["displacements"])
    assert np.asarray(out["nodes"]).shape == u.shape == (1000, 3)
    assert out["settled"] and not out["diverged"] and 0 < out["steps"] <= 2000
    problem = fpm.load_problem(spec)
    assert out["perturbed"] == len(fpm_model(problem).perturbed_list(0, 10).order)
    assert np.all(u[problem.fixed] == 0)
    pulled = problem.load_cases[0].nodes
    assert np.all(u[pulled, 2] > 0)  # the pulled nodes moved along +z
