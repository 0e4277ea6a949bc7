"""The static equilibrium of the FPM (:mod:`fpm.dynamics.equilibrium`) against mathematics and
against the dynamic settle.

Mathematics: analytic answers of springs and chains (also after a 90 degree rotation), exact
scaling u(k, F) = u(2k, 2F), the residual recomputed independently from the springs,
finite-difference checks of the energy's gradient and tangent, and the clamped tangent's
positive semi-definiteness.

Dynamic settle: on the paper's cube (10x10x10 nodes, `full`), fpm.simulate with a settle
tolerance of 1e-8 against the static solve at its default tolerance (settle_tolerance / 10 =
1e-6 of the largest applied force). Measured there, the two differ by at most 7e-7 of the
largest displacement at any node and by 1.7e-6 of the summed displacement (Eq. 2 style; 2.8e-6
with family stiffnesses); the bound is 1e-5 there, a margin of 4-10, tighter where the measured
difference is smaller, while anything that changes the physics (a wrong stiffness scale,
family, depth or load) moves the answer by percents.
"""

from __future__ import annotations

import copy
import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_fpm import box_spec, chain_spec, network_spec, spring_forces

import fpm
import fpm.dynamics.newton as newton
from fpm.dynamics.equilibrium import (
    Equilibrium,
    EquilibriumError,
    StaticSolver,
    static_equilibrium,
    static_solver,
)
from fpm.dynamics.spring_system import Params, SpringSystem
from fpm.fem.linear_solver import ReusedHierarchy
from fpm.model.forces import Stiffness
from fpm.model.stiffness import spring_stiffness
from fpm.model.volume import cell_volumes

ROOT = Path(__file__).resolve().parents[2]
PAPER_A: dict[str, Any] = json.loads((ROOT / "examples" / "paper-material-a.json").read_text())
K_A = 38.8
"""N/m, about the single k that fits material A."""
D_A = 0.3
"""N s/m: settles material A's cube quickly at the spec's dt."""
AGREE = 1e-5
"""Static vs dynamic bound, relative (see the module docstring)."""


def paper_problem(**fpm_settings: Any) -> fpm.Problem:
    spec = copy.deepcopy(PAPER_A)
    spec["fpm"].update(fpm_settings)
    return fpm.load_problem(spec)


@pytest.fixture(scope="module")
def paper() -> fpm.Problem:
    return paper_problem()


def unbalanced(problem: fpm.Problem, result: Equilibrium, k: float | np.ndarray) -> np.ndarray:
    """(N,) |F_i + F_s| at the result, computed from scratch (helpers_fpm.spring_forces)."""
    x = problem.nodes + result.displacements
    applied = problem.load_cases[result.load_case].dense(problem.n_nodes)
    gravity = np.asarray(problem.spec.fpm.gravity)
    applied += problem.solid.masses[:, None] * gravity[None, :]
    fs = spring_forces(x, problem.solid.springs, problem.rest_lengths, k)
    return np.linalg.norm(applied + fs, axis=1)


def assert_agree(static: np.ndarray, dynamic: np.ndarray, bound: float = AGREE) -> None:
    """Largest nodal and summed (Eq. 2 style) difference, relative to the displacements."""
    norm_s = np.linalg.norm(dynamic, axis=1)
    diff = np.linalg.norm(static - dynamic, axis=1)
    assert norm_s.max() > 0
    assert diff.max() <= bound * norm_s.max(), diff.max() / norm_s.max()
    assert diff.sum() <= bound * norm_s.sum(), diff.sum() / norm_s.sum()


def settle(problem: fpm.Problem, k: Any, load_case: int, depth: int | None = None):
    result = fpm.simulate(
        problem,
        k=k,
        d=D_A,
        load_case=load_case,
        depth=depth,
        settle_tolerance=1e-8,
        max_steps=100_000,
    )
    assert result.settled
    return result


# --- analytic answers -----------------------------------------------------------------------


def test_single_spring_stretches_by_f_over_k():
    f, k = 0.01, 10.0
    problem = fpm.load_problem(chain_spec(1, 0.01, (1, 0, 0), tip_force=[f, 0, 0]))
    result = static_equilibrium(problem, k=k)
    assert result.converged and result.perturbed == 1
    assert result.displacements[1] == pytest.approx([f / k, 0, 0], abs=1e-6 * f / k)
    assert result.displacements[0] == pytest.approx([0, 0, 0], abs=0)


@pytest.mark.parametrize("n", [2, 5])
def test_chain_in_series_stretches_each_spring_by_f_over_k(n: int):
    """Oblique chain: node i moves i F / k along the chain (the settle criterion's bound on a
    chain: n(n+1)/2 * residual / k at the tip)."""
    f, k, direction = 0.02, 25.0, np.array([1.0, 2.0, 2.0]) / 3
    spec = chain_spec(n, 0.01, tuple(direction), tip_force=list(f * direction))
    result = static_equilibrium(fpm.load_problem(spec), k=k)
    assert result.converged
    expected = np.arange(n + 1)[:, None] * (f / k) * direction[None, :]
    slack = n * (n + 1) / 2 * result.tolerance * f / k
    assert result.displacements == pytest.approx(expected, abs=slack)


@pytest.mark.parametrize(("scale", "factor"), [((1.0, 1.0, 1.0), 1.0), ((1.0, 1.0, 2.0), 2.0)])
def test_axis_lattice_bar_stretches_like_four_chains(scale, factor):
    """A 2 x 2 x 6 `axis` lattice, face z- fixed, +z force f on each end node: four parallel
    chains of 5 springs (stiffness k times the scale along z), the lateral springs unstretched;
    level i moves i f / (factor k). The lattice is a mechanism (no shear stiffness), so the
    tangent is singular: this is the shifted-tangent path."""
    f, k, h, cells = 0.01, 10.0, 0.01, 5
    top = cells * h
    forces = [{"at": [i * h, j * h, top], "vector": [0, 0, f]} for i in (0, 1) for j in (0, 1)]
    spec = box_spec(
        (2, 2, cells + 1),
        h,
        connectivity="axis",
        forces=forces,
        fpm_settings={"stiffness_scale": list(scale)},
    )
    problem = fpm.load_problem(spec)
    result = static_equilibrium(problem, k=k)
    assert result.converged, result.message
    level = np.rint(problem.nodes[:, 2] / h)
    slack = cells * (cells + 1) / 2 * result.tolerance * f / k
    assert result.displacements[:, 2] == pytest.approx(level * f / (factor * k), abs=slack)
    assert np.abs(result.displacements[:, :2]).max() <= slack


def test_spring_rotates_onto_a_lateral_force():
    """Geometric nonlinearity: a spring along x pulled along y turns through 90 degrees and
    stretches by F / k; its free end ends at (0, L + F / k, 0). (At rest the spring has no
    lateral stiffness: the tangent is singular, so this also exercises the shifted tangent.)
    A third, fixed node keeps the solid's size above the distance moved."""
    length, f, k = 0.01, 0.01, 10.0
    spec = network_spec(
        [[0, 0, 0], [length, 0, 0], [0, 3 * length, 0]],
        [(0, 1), (0, 2)],
        fixed_nodes=[0, 2],
        forces={1: [0, f, 0]},
    )
    problem = fpm.load_problem(spec)
    result = static_equilibrium(problem, k=k)
    assert result.converged, result.message
    end = problem.nodes[1] + result.displacements[1]
    assert end == pytest.approx([0, length + f / k, 0], abs=1e-5 * length)


def test_an_equilibrium_beyond_the_solid_size_is_not_converged():
    """The same rotation on the spring alone: the end moves 1.49 L, further than the solid's
    size L; a dynamic run stops there as diverged, so the static answer is not converged."""
    problem = fpm.load_problem(chain_spec(1, 0.01, (1, 0, 0), tip_force=[0, 0.01, 0]))
    result = static_equilibrium(problem, k=10.0)
    assert not result.converged and "size" in result.message
    with pytest.raises(EquilibriumError, match="size"):
        result.check()


def test_an_unheld_solid_fails_clearly():
    """No fixed node: the force accelerates the spring away; there is no equilibrium."""
    spec = network_spec([[0, 0, 0], [0.01, 0, 0]], [(0, 1)], forces={1: [0.01, 0, 0]})
    result = static_equilibrium(fpm.load_problem(spec), k=10.0)
    assert not result.converged and result.message


def test_gives_up_after_the_iteration_limit(paper: fpm.Problem, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(newton, "MAX_ITERATIONS", 1)
    result = StaticSolver(paper).solve(2, spring_stiffness(paper, K_A), None)
    assert not result.converged and result.iterations == 1
    assert "no convergence in 1 Newton iterations" in result.message
    assert result.residual > result.tolerance * 1.0


# --- exact scaling and the residual ---------------------------------------------------------


def test_doubling_stiffness_and_forces_keeps_the_displacements(paper: fpm.Problem):
    """u(k, F) = u(2k, 2F) exactly (the equilibrium equations are homogeneous in (k, F)); both
    solves stop at a residual of 1e-6 of their own load, which maps to ~1e-6 of u."""
    spec = copy.deepcopy(PAPER_A)
    for case in spec["load_cases"]:
        for force in case["forces"]:
            force["vector"] = [2 * v for v in force["vector"]]
    doubled = fpm.load_problem(spec)
    for case in (0, 2):
        base = StaticSolver(paper).solve(case, spring_stiffness(paper, K_A), None)
        scaled = StaticSolver(doubled).solve(case, spring_stiffness(doubled, 2 * K_A), None)
        assert base.converged and scaled.converged
        u = np.abs(base.displacements).max()
        assert scaled.displacements == pytest.approx(base.displacements, abs=1e-5 * u)


@pytest.mark.parametrize("amg_from", [10**9, 0])
def test_the_linear_response_is_the_small_load_limit_of_the_equilibrium(
    paper: fpm.Problem, amg_from
):
    """The model linearised at rest (:meth:`StaticSolver.linear_response`, what the validation's
    large-deformation note compares with) is the limit of u(s F) / s as s -> 0, the gap
    shrinking in proportion to s (the springs' rotation and stretch are first order in the
    load), by LU and by multigrid CG alike; linear: twice the forces, twice the answer; and CG
    started from the equilibrium lands on the same answer."""
    k = spring_stiffness(paper, K_A)
    solver = StaticSolver(paper, amg_from=amg_from)
    loads = solver.loads(2)
    linear = solver.linear_response(2, k, None, loads, rtol=1e-12)
    size = np.abs(linear).max()
    gaps = []
    for s in (1e-1, 1e-2):
        spec = copy.deepcopy(PAPER_A)
        for case in spec["load_cases"]:
            for force in case["forces"]:
                force["vector"] = [s * v for v in force["vector"]]
        small = fpm.load_problem(spec)
        found = StaticSolver(small).solve(2, k, None, tolerance=1e-10)
        assert found.converged
        gaps.append(np.abs(found.displacements / s - linear).max() / size)
    assert gaps[1] < 1e-2 and gaps[0] / gaps[1] == pytest.approx(10, rel=0.15)
    twice = solver.linear_response(2, k, None, 2 * loads, rtol=1e-12)
    assert twice == pytest.approx(2 * linear, abs=1e-8 * size)
    full = solver.solve(2, k, None, tolerance=1e-10).displacements  # CG started there instead
    started = solver.linear_response(2, k, None, loads, guess=full, rtol=1e-12)
    assert np.abs(full - linear).max() > 1e-3 * size  # the paper's loads are not linear
    assert started == pytest.approx(linear, abs=1e-8 * size)


def test_the_residual_is_below_the_tolerance_recomputed_from_the_springs(paper: fpm.Problem):
    result = static_equilibrium(paper, k=K_A, load_case=2, depth=None)
    assert result.converged and result.tolerance == pytest.approx(1e-6)
    free = ~paper.fixed
    forces = unbalanced(paper, result, K_A)
    f_max = np.linalg.norm(paper.load_cases[2].forces, axis=1).max()
    assert forces[free].max() <= result.tolerance * f_max
    assert forces[free].max() == pytest.approx(result.residual, rel=1e-3)
    # Not trivially: the springs carry loads far above the residual, and the nodes move.
    assert np.abs(result.displacements).max() > 0.5 * paper.h
    assert result.perturbed == free.sum() and result.depth == 8


def test_only_the_perturbed_list_moves(paper: fpm.Problem):
    result = static_equilibrium(paper, k=K_A, load_case=1, depth=2)
    plist = static_solver(paper).lists.get(paper.load_cases[1].nodes, 2)
    moved = np.flatnonzero(np.any(result.displacements != 0, axis=1))
    assert set(moved) == set(plist.order.tolist())
    assert result.perturbed == len(plist.order) and result.depth == 2
    assert not np.any(result.displacements[paper.fixed])


def test_depth_zero_moves_only_the_stimulated_nodes(paper: fpm.Problem):
    result = static_equilibrium(paper, k=K_A, depth=0)
    assert result.converged and result.perturbed == 4 and result.depth == 0
    assert set(np.flatnonzero(np.any(result.displacements != 0, axis=1))) == set(
        paper.load_cases[0].nodes.tolist()
    )


# --- derivatives ----------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["single", "families+volume"])
def strained_block(
    request,
) -> tuple[SpringSystem, np.ndarray, Params, np.ndarray]:
    """A 3x3x4 `full` block's system at a random state with stretched and compressed springs,
    random stiffnesses and forces: springs only (the paper's model), or with the volume term
    (random kappa per cell, cells grown and shrunk)."""
    mode = request.param
    problem = fpm.load_problem(box_spec((3, 3, 4), 0.01, fpm_settings={"stiffness": mode}))
    system, _ = StaticSolver(problem).system(0, None)
    rng = np.random.default_rng(7)
    u = rng.normal(0, 0.002, (system.n_free, 3))
    springs = rng.uniform(5, 20, len(problem.solid.springs))
    kappa = None
    if mode == "families+volume":
        kappa = rng.uniform(1e3, 1e4, len(problem.solid.elements()))
    k = system.parameters(Stiffness(springs, kappa))
    forces = rng.normal(0, 0.01, (system.n_free, 3))
    stretch = system.stretch(u)
    assert (stretch < 0).sum() > 20 and (stretch > 0).sum() > 20
    if kappa is not None:
        assert system.cells is not None and len(system.cell_ids) == 12
        padded = np.zeros((problem.n_nodes, 3))
        padded[system.free] = u
        change = cell_volumes(system.cells, padded)
        assert (change < 0).sum() >= 2 and (change > 0).sum() >= 2
    return system, u, k, forces


def test_gradient_is_the_derivative_of_the_energy(strained_block):
    system, u, k, forces = strained_block
    gradient = system.gradient(u, k, forces)
    eps = 1e-7
    rng = np.random.default_rng(1)
    for _ in range(5):
        v = rng.normal(size=u.shape)
        numeric = system.energy(u + eps * v, k, forces) - system.energy(u - eps * v, k, forces)
        numeric /= 2 * eps
        assert np.einsum("ij,ij->", gradient, v) == pytest.approx(numeric, rel=1e-6)


def test_energy_change_equals_the_difference_of_energies(strained_block):
    system, u, k, forces = strained_block
    step = np.random.default_rng(2).normal(0, 0.001, u.shape)
    exact = system.energy(u + step, k, forces) - system.energy(u, k, forces)
    assert system.energy_change(u, step, k, forces) == pytest.approx(exact, rel=1e-10)


def test_exact_tangent_is_the_derivative_of_the_gradient(strained_block):
    system, u, k, forces = strained_block
    tangent = system.tangent(u, k, modified=False)
    assert abs(tangent - tangent.T).max() < 1e-12 * abs(tangent).max()
    eps = 1e-7
    v = np.random.default_rng(3).normal(size=u.shape)
    numeric = system.gradient(u + eps * v, k, forces) - system.gradient(u - eps * v, k, forces)
    numeric /= 2 * eps
    assert tangent @ v.ravel() == pytest.approx(numeric.ravel(), rel=1e-6, abs=1e-8)


def test_clamped_tangent_is_positive_semidefinite_and_above_the_exact_one(strained_block):
    system, u, k, _ = strained_block
    exact = system.tangent(u, k, modified=False).toarray()
    clamped = system.tangent(u, k, modified=True).toarray()
    scale = np.abs(clamped).max()
    assert np.linalg.eigvalsh(exact).min() < -1e-3 * scale  # compressed springs: indefinite
    assert np.linalg.eigvalsh(clamped).min() > -1e-12 * scale
    if k.kappa is None:  # the cells' dropped pressure term has no sign
        assert np.linalg.eigvalsh(clamped - exact).min() > -1e-12 * scale
    # Reduced (Galerkin) tangent: Q^T K Q of the clamped tangent.
    q = np.linalg.qr(np.random.default_rng(4).normal(size=(3 * system.n_free, 5)))[0]
    reduced = system.reduced_tangent(u, k, np.ascontiguousarray(q.reshape(-1, 3, 5)), True)
    assert reduced == pytest.approx(q.T @ clamped @ q, rel=1e-10, abs=1e-10 * scale)


# --- against the dynamic settle --------------------------------------------------------------


@pytest.mark.parametrize("case", [0, 2], ids=["0.25N", "1.0N"])
def test_paper_cube_agrees_with_the_dynamic_settle(paper: fpm.Problem, case: int):
    """At 1.0 N per node the pulled nodes move ~0.95 h and the springs around them rotate."""
    static = static_equilibrium(paper, k=K_A, load_case=case, depth=None)
    dynamic = settle(paper, K_A, case)
    assert static.converged and static.perturbed == dynamic.perturbed
    assert_agree(static.displacements, dynamic.displacements)
    if case == 2:
        assert np.linalg.norm(dynamic.displacements, axis=1).max() > 0.9 * paper.h
        # the linear answer (1 N = 4 x 0.25 N) is off by far more than the bound
        small = static_equilibrium(paper, k=K_A, load_case=0, depth=None)
        with pytest.raises(AssertionError):
            assert_agree(4 * small.displacements, dynamic.displacements, 100 * AGREE)


def test_anisotropic_lattice_agrees_with_the_dynamic_settle():
    problem = paper_problem(stiffness_scale=[1.0, 1.0, 2.0])
    static = static_equilibrium(problem, k=K_A, load_case=2, depth=None)
    dynamic = settle(problem, K_A, 2)
    assert_agree(static.displacements, dynamic.displacements)
    # the scale matters: the isotropic answer is far off
    isotropic = static_equilibrium(paper_problem(), k=K_A, load_case=2, depth=None)
    assert (
        np.abs(isotropic.displacements - static.displacements).max()
        > 0.05 * np.abs(static.displacements).max()
    )


def test_family_stiffnesses_agree_with_the_dynamic_settle():
    problem = paper_problem(stiffness="families")
    theta = [30.0, 20.0, 10.0]
    static = static_equilibrium(problem, k=theta, load_case=2, depth=None)
    dynamic = settle(problem, theta, 2)
    assert_agree(static.displacements, dynamic.displacements)
    k = spring_stiffness(problem, theta)
    free = ~problem.fixed
    assert unbalanced(problem, static, k)[free].max() <= static.tolerance * 1.0


@pytest.mark.parametrize(("depth", "bound"), [(1, 5e-7), (2, 1e-6), (4, 3e-6)])
def test_shallow_lists_agree_with_the_dynamic_settle(paper: fpm.Problem, depth: int, bound: float):
    """Shorter lists are stiffer, so the same residual moves them less: measured 4e-8, 9e-8
    and 7e-7 (summed) for depths 1, 2 and 4."""
    static = static_equilibrium(paper, k=K_A, load_case=2, depth=depth)
    dynamic = settle(paper, K_A, 2, depth)
    assert static.perturbed == dynamic.perturbed and static.depth == dynamic.depth == depth
    assert_agree(static.displacements, dynamic.displacements, bound)


def test_gravity_agrees_with_the_dynamic_settle():
    """Node weights join the applied forces (and the tolerance's largest applied force)."""
    spec = box_spec(
        (4, 4, 5),
        0.01,
        forces=[{"at": [0.01, 0.01, 0.04], "vector": [0.002, 0.0, 0.01]}],
        fpm_settings={"gravity": [0.0, 0.0, -9.81]},
    )
    problem = fpm.load_problem(spec)
    static = static_equilibrium(problem, k=10.0)
    dynamic = fpm.simulate(problem, k=10.0, d=0.05, settle_tolerance=1e-9, max_steps=200_000)
    assert dynamic.settled and static.converged
    assert_agree(static.displacements, dynamic.displacements, 1e-6)  # measured 2e-7
    assert static.displacements[:, 2].sum() < 0  # the weight pulls the block down overall


# --- warm starts, the multigrid path, the module function -----------------------------------


def test_a_warm_start_is_faster_and_lands_on_the_cold_answer(paper: fpm.Problem):
    k1 = spring_stiffness(paper, 1.05 * K_A)
    cold = StaticSolver(paper, warm=False).solve(2, k1, None)
    solver = StaticSolver(paper)
    solver.solve(2, spring_stiffness(paper, K_A), None)
    warm = solver.solve(2, k1, None)
    assert cold.start == "rest" and warm.start == "predicted"
    assert warm.converged and warm.iterations < cold.iterations
    u = np.abs(cold.displacements).max()
    assert warm.displacements == pytest.approx(cold.displacements, abs=1e-5 * u)


def test_full_depth_by_its_number_shares_the_warm_starts_of_none(paper: fpm.Problem):
    """Full depth asked as None and as its number is one list: the second solve at the same
    stiffness starts at the first's answer and takes no Newton step; a shallower list keeps
    its own warm starts (it starts from rest)."""
    from fpm.fitting.bounds import full_depth

    deepest = full_depth(paper)
    k = spring_stiffness(paper, K_A)
    solver = StaticSolver(paper)
    first = solver.solve(2, k, None)
    again = solver.solve(2, k, deepest)
    assert first.iterations > 0 and again.iterations == 0 and again.start == "predicted"
    assert np.array_equal(again.displacements, first.displacements)
    shallow = solver.solve(2, k, deepest - 3)
    assert shallow.start == "rest" and shallow.iterations > 0


def test_keep_only_forgets_the_probes_and_keeps_the_chosen_depth(paper: fpm.Problem):
    """After the depth search, keep_only(depth) drops the other lists' systems with their
    warm starts (a probe asked again starts from rest) and keeps the chosen one's: its next
    solve is the same to the bit as without keep_only (no Newton step, the warm answer)."""
    from fpm.fitting.bounds import full_depth

    deepest = full_depth(paper)
    k = spring_stiffness(paper, K_A)
    solvers = [StaticSolver(paper), StaticSolver(paper)]
    for solver in solvers:
        solver.solve(2, k, None)
        solver.solve(2, k, deepest - 3)
    solvers[0].keep_only(deepest)
    assert len(solvers[0]._systems) == 1 and len(solvers[1]._systems) == 2
    kept, other = (solver.solve(2, k, deepest) for solver in solvers)
    assert kept.iterations == 0 and kept.start == "predicted"
    assert np.array_equal(kept.displacements, other.displacements)
    probe = solvers[0].solve(2, k, deepest - 3)
    assert probe.start == "rest" and probe.iterations > 0


def test_a_seeded_equilibrium_is_taken_as_it_is(paper: fpm.Problem):
    """An equilibrium solved by another solver (a chain's, in another process) seeded into a
    fresh one: its solve at the same stiffness takes no Newton step and returns it to the bit;
    a solver with warm starts off ignores the seed."""
    k = spring_stiffness(paper, K_A)
    solved = StaticSolver(paper).solve(2, k, None)
    fresh = StaticSolver(paper)
    fresh.seed(2, k, None, solved.displacements)
    again = fresh.solve(2, k, None)
    assert again.start == "predicted" and again.iterations == 0
    assert np.array_equal(again.displacements, solved.displacements)
    cold = StaticSolver(paper, warm=False)
    cold.seed(2, k, None, solved.displacements)
    assert cold.solve(2, k, None).start == "rest"


def test_a_shallow_list_seeded_from_full_depth_lands_on_its_cold_answer(paper: fpm.Problem):
    """A depth probe started from the full-depth equilibrium restricted to its list (the depth
    search's start) needs fewer Newton steps than from rest and lands on the same answer."""
    from fpm.fitting.bounds import full_depth

    depth = full_depth(paper) - 3
    k = spring_stiffness(paper, K_A)
    full = StaticSolver(paper).solve(2, k, None)
    cold = StaticSolver(paper).solve(2, k, depth)
    seeded = StaticSolver(paper)
    seeded.seed(2, k, depth, full.displacements)
    warm = seeded.solve(2, k, depth)
    assert warm.converged and warm.start == "predicted"
    assert warm.iterations < cold.iterations
    u = np.abs(cold.displacements).max()
    assert warm.displacements == pytest.approx(cold.displacements, abs=1e-5 * u)


def test_proportional_stiffnesses_are_interpolated_exactly_enough(paper: fpm.Problem):
    """With one k, earlier solutions lie on the curve u(k, s F): three of them and s = 0
    interpolate a fourth so well that no Newton step is needed."""
    solver = StaticSolver(paper)
    for factor in (0.9, 1.0, 1.1):
        solver.solve(2, spring_stiffness(paper, factor * K_A), None)
    again = solver.solve(2, spring_stiffness(paper, 1.03 * K_A), None)
    assert again.converged and again.iterations == 0
    cold = StaticSolver(paper, warm=False).solve(2, spring_stiffness(paper, 1.03 * K_A), None)
    u = np.abs(cold.displacements).max()
    assert again.displacements == pytest.approx(cold.displacements, abs=1e-5 * u)


def test_family_changes_start_from_the_reduced_model():
    problem = paper_problem(stiffness="families")
    solver = StaticSolver(problem)
    rng = np.random.default_rng(5)
    theta = np.array([30.0, 20.0, 10.0])
    for _ in range(6):
        solver.solve(2, spring_stiffness(problem, theta * rng.uniform(0.9, 1.1, 3)), None)
    k = spring_stiffness(problem, theta)
    warm = solver.solve(2, k, None)
    cold = StaticSolver(problem, warm=False).solve(2, k, None)
    assert warm.converged and warm.iterations < cold.iterations
    u = np.abs(cold.displacements).max()
    assert warm.displacements == pytest.approx(cold.displacements, abs=1e-5 * u)


def test_multigrid_path_equals_the_direct_path(paper: fpm.Problem):
    k = spring_stiffness(paper, K_A)
    direct = StaticSolver(paper, amg_from=10**9).solve(2, k, 4, tolerance=1e-10)
    iterative = StaticSolver(paper, amg_from=0).solve(2, k, 4, tolerance=1e-10)
    assert direct.linear_iterations == 0 and iterative.linear_iterations > 0
    assert direct.converged and iterative.converged
    u = np.abs(direct.displacements).max()
    assert iterative.displacements == pytest.approx(direct.displacements, abs=1e-8 * u)


def test_one_multigrid_hierarchy_serves_steps_stiffnesses_and_load_cases(paper: fpm.Problem):
    solver = StaticSolver(paper, amg_from=0)
    for factor in (1.0, 1.3, 0.7):
        for case in range(3):
            result = solver.solve(case, spring_stiffness(paper, factor * K_A), None)
            assert result.converged
            assert result.linear_iterations > 0 or result.iterations == 0
    assert solver.hierarchies_built == 1
    solver.solve(0, spring_stiffness(paper, K_A), 3)  # another list: its own hierarchy
    assert solver.hierarchies_built == 2


def test_a_hierarchy_that_slows_down_is_rebuilt():
    """CG iterations per digit of residual reduction, against the first solve's."""
    multigrid = ReusedHierarchy(hierarchy=None)
    multigrid.record(10, 1e-2, True)  # 5 per digit
    multigrid.record(11, 1e-2, True)
    assert not multigrid.stale
    multigrid.record(13, 1e-1, True)  # 13 > 2 * 5 + 2
    assert multigrid.stale
    fresh = ReusedHierarchy(hierarchy=None)
    fresh.record(4, 1e-2, True)
    fresh.record(300, 0.5, False)  # hit the iteration limit
    assert fresh.stale


def test_static_equilibrium_reads_the_spec(paper: fpm.Problem):
    """depth None = the spec's (10 here; the cube has 8 layers below the pulled nodes);
    'auto' = all layers."""
    full = static_equilibrium(paper, k=K_A, load_case=0)
    assert full.depth == 8 and full.load_case == 0
    auto = paper_problem(depth="auto")
    assert static_equilibrium(auto, k=K_A).perturbed == full.perturbed
    loose = static_equilibrium(paper, k=K_A, tolerance=1e-3)
    assert loose.tolerance == 1e-3 and loose.residual <= 1e-3 * 0.25


def test_static_equilibrium_refuses_bad_arguments(paper: fpm.Problem):
    with pytest.raises(ValueError, match="load_case"):
        static_equilibrium(paper, k=K_A, load_case=3)
    with pytest.raises(ValueError, match="k > 0"):
        static_equilibrium(paper, k=0.0)
    with pytest.raises(ValueError, match="give 3 values"):
        static_equilibrium(paper_problem(stiffness="families"), k=[1.0, 2.0])
    with pytest.raises(ValueError, match="one stiffness per spring"):
        StaticSolver(paper).solve(0, np.ones(3), None)
    with pytest.raises(ValueError, match="tolerance"):
        static_equilibrium(paper, k=K_A, tolerance=0.0)


def test_one_cached_solver_per_thread(paper: fpm.Problem):
    mine = static_solver(paper)
    assert static_solver(paper) is mine
    theirs: list[StaticSolver] = []
    thread = threading.Thread(target=lambda: theirs.append(static_solver(paper)))
    thread.start()
    thread.join()
    assert theirs[0] is not mine and theirs[0].problem is paper


def test_solvers_on_threads_share_one_system_and_agree_with_a_solver_alone():
    """Two solvers of one problem, each on its own thread, hold the same (read-only) spring
    system and each its own tangent buffer; their answers equal a lone solver's to the bit;
    the shared system goes once no solver keeps it."""
    import gc

    problem = paper_problem(depth="auto")
    k = [spring_stiffness(problem, f * K_A) for f in (1.0, 1.2)]
    expected = [
        StaticSolver(paper_problem(depth="auto"), amg_from=0).solve(2, k[i], None).displacements
        for i in range(2)
    ]
    solvers = [StaticSolver(problem, amg_from=0) for _ in range(2)]
    answers: list[np.ndarray | None] = [None, None]

    def run(i: int, solver: StaticSolver) -> None:
        answers[i] = solver.solve(2, k[i], None).displacements

    threads = [threading.Thread(target=run, args=(i, s)) for i, s in enumerate(solvers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(2):
        assert np.array_equal(answers[i], expected[i])
    first, second = (s.system(2, None)[0] for s in solvers)
    assert first is second
    assert solvers[0]._buffers.keys() == solvers[1]._buffers.keys()
    key = next(iter(solvers[0]._buffers))
    assert solvers[0]._buffers[key] is not solvers[1]._buffers[key]
    del first, second, solvers, threads
    gc.collect()
    assert len(problem.cache.spring_systems) == 0
