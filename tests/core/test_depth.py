"""Depth 'auto' (fpm.fitting.damping.depth): the cost test and the model's own response test."""

from __future__ import annotations

import dataclasses

import numpy as np

import fpm
from fpm.dynamics.equilibrium import StaticSolver
from fpm.fitting.bounds import fit_depth, full_depth
from fpm.fitting.cost import StaticCost
from fpm.fitting.damping.depth import OwnResponses, resolve_depth
from fpm.model.stiffness import continuum_start, model_stiffness

TOLERANCE = 0.005


def bar_problem(depth: str = "auto") -> fpm.Problem:
    """A soft bar 15 x 3 x 2 cm on its bottom face, pressed at one end: its response fades
    along the bar, so a list can stop before the far end."""
    return fpm.load_problem({
        "name": "bar on a table",
        "material": {"youngs_modulus": 5000.0, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {"type": "box", "size": [0.15, 0.03, 0.02], "nodes": [16, 4, 3],
                     "connectivity": "full"},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"at": [0.0, 0.01, 0.02], "vector": [0, 0, -0.001]}]}],
        "fpm": {"depth": depth, "auto_depth_tolerance": TOLERANCE},
    })  # fmt: skip


def own_change(problem: fpm.Problem, theta: list[float], depth: int) -> float:
    """The largest relative change (Eq. 2's norm), over x, y and z, of the lattice's linear
    response to the load case's force magnitudes at ``depth`` against every layer's, each
    solved from scratch on a fresh solver."""
    solver = StaticSolver(problem, warm=False)
    stiffness = model_stiffness(problem, theta)
    magnitudes = np.linalg.norm(problem.load_cases[0].dense(problem.n_nodes), axis=1)
    worst = 0.0
    for a in range(3):
        loads = np.zeros((problem.n_nodes, 3))
        loads[:, a] = magnitudes
        full = solver.linear_response(0, stiffness, None, loads)
        cut = solver.linear_response(0, stiffness, depth, loads)
        change = np.linalg.norm(cut - full, axis=1).sum() / np.linalg.norm(full, axis=1).sum()
        worst = max(worst, float(change))
    return worst


def test_the_models_own_response_decides_where_the_cost_cannot_tell():
    """Against a reference that every cut list matches better (the full-depth equilibrium
    mirrored: a shorter list moves less, so its cost falls), the cost test passes every depth;
    the answer is then the smallest depth whose own response along x, y and z stays within
    tolerance x the relative discrepancy (200% here: 1%) of full depth's, one layer less
    beyond it, and it cuts the bar short of its far end."""
    problem = bar_problem()
    theta = continuum_start(problem)
    mirrored = (
        -StaticCost(problem, np.zeros((1, problem.n_nodes, 3)), None)
        .displacements(theta, 0, None)
        .displacements[None]
    )
    cost = StaticCost(problem, mirrored, None)
    depth, deepest, probed = resolve_depth(cost, theta, TOLERANCE)
    assert 0 < depth < deepest == full_depth(problem)
    allowed = TOLERANCE * 2.0
    assert own_change(problem, theta, depth) <= allowed < own_change(problem, theta, depth - 1)
    full = cost(theta, None).case_costs[0]
    assert cost(theta, depth - 1).case_costs[0] <= full  # the cost test alone would cut more


def test_the_share_beyond_the_list_bounds_the_change_from_below():
    """A cut list holds the nodes beyond it at rest, so the share of full depth's response
    out there is at most the change: the bound that refuses a depth without a solve."""
    problem = bar_problem()
    theta = continuum_start(problem)
    cost = StaticCost(problem, np.ones((1, problem.n_nodes, 3)), None)
    responses = OwnResponses.at_full_depth(cost, model_stiffness(problem, theta), [1.0], TOLERANCE)
    assert responses is not None
    pattern = responses.patterns[0]
    for depth in range(1, full_depth(problem)):
        responses.keeps(depth)
        assert 0 < pattern.beyond(depth) <= pattern.changes[depth]
        assert np.isclose(pattern.changes[depth], own_change(problem, theta, depth), rtol=1e-5)


def test_the_default_depth_is_every_layer():
    problem = bar_problem(depth="full")
    assert fpm.load_problem({**problem.spec.model_dump(), "fpm": {}}).spec.fpm.depth == "full"
    assert fit_depth(problem) is None
    assert problem.spec.fpm.layers is None
    assert fpm.load_problem({**problem.spec.model_dump(), "fpm": {"depth": 4}}).spec.fpm.layers == 4


def test_no_equilibrium_at_full_depth_keeps_full_depth(monkeypatch):
    """A stiffness with no finite cost at full depth (a load case diverged: its case costs stop
    there, shorter than the load cases) leaves nothing to cut against: full depth, no probe.
    (A fuzzed spec, nu -0.999 on a 2 x 3 x 2 bar 1 m long, ended in a ValueError of zip.)"""
    problem = bar_problem()
    theta = continuum_start(problem)
    cost = StaticCost(problem, np.zeros((1, problem.n_nodes, 3)), None)
    called = []
    real = StaticCost.__call__

    def diverged_at_full_depth(self, theta, depth=None):
        called.append(depth)
        ev = real(self, theta, depth)
        return dataclasses.replace(ev, cost=float("inf"), case_costs=[]) if depth is None else ev

    monkeypatch.setattr(StaticCost, "__call__", diverged_at_full_depth)
    depth, deepest, probed = resolve_depth(cost, theta, TOLERANCE)
    assert depth == deepest == full_depth(problem) and probed == {deepest: []}
    assert called == [None]
