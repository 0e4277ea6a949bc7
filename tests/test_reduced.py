"""Stage 1's reduced linear model (fpm.fitting.reduced) against mathematics: the lattice's
stiffness at rest is linear in the fitted parameters (the shared-pattern K(theta) is the
tangent assembled at theta), and the reduced model is exact on a basis that holds the exact
response (Galerkin)."""

from __future__ import annotations

import numpy as np
from helpers_fpm import box_spec

import fpm
from fpm.fitting.cost import StaticCost
from fpm.fitting.reduced import RTOL, ReducedLinearModel
from fpm.model.stiffness import continuum_start, family_names, model_stiffness


def problem_and_cost(force: float = 0.01) -> tuple[fpm.Problem, StaticCost]:
    """A 5x4x6 `full` box, face z- fixed, families+volume; two load cases at the top; the
    reference is the FEM's (linear, selective)."""
    spec = box_spec(
        (5, 4, 6), 0.01,
        forces=[{"at": [0.02, 0.01, 0.05], "vector": [0.0, 0.0, -force]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["load_cases"].append({"forces": [{"at": [0.04, 0.03, 0.05], "vector": [force, 0.0, 0.0]}]})
    spec["material"]["poisson_ratio"] = 0.45
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    return problem, StaticCost(problem, reference.displacements, None)


def test_the_stiffness_at_rest_is_linear_in_the_parameters():
    """K(theta) from the shared unit matrices equals the tangent at rest assembled at theta."""
    problem, cost = problem_and_cost()
    theta = np.array(continuum_start(problem)) * np.array([1.3, 0.7, 50.0, 1.1])
    model = ReducedLinearModel(cost, list(theta))
    system, _ = cost.solver.system(0, None)
    direct = system.tangent(np.zeros((system.n_free, 3)), system.parameters(
        model_stiffness(problem, theta)), modified=True)  # fmt: skip
    combined = model.cases[0].unit.at(theta)
    scale = np.abs(direct.toarray()).max()
    assert np.abs((combined - direct).toarray()).max() < 1e-12 * scale
    units = model.cases[0].unit
    assert len(units) == len(family_names(problem))
    for p, e in enumerate(np.eye(len(units))):  # each K_p alone, on its own nonzero blocks
        alone = system.tangent(np.zeros((system.n_free, 3)), system.parameters(
            model_stiffness(problem, e)), modified=True)  # fmt: skip
        assert np.array_equal(units.matrix(p).toarray(), alone.toarray())
    # a family's springs touch fewer blocks than the cells, which touch all of the pattern
    assert [len(u.positions) for u in units.units][-1] == units.n_blocks
    assert all(len(u.positions) < units.n_blocks for u in units.units[:-1])


def test_the_reduced_model_is_exact_where_its_basis_holds_the_response():
    """Enriched at theta, the reduced linear displacements at theta equal the full linear
    solve there (Galerkin projection on a basis that contains the solution, which the
    enrichment solved to a relative residual of RTOL)."""
    problem, cost = problem_and_cost()
    start = continuum_start(problem)
    model = ReducedLinearModel(cost, start)
    theta = np.array(start) * np.array([0.8, 1.2, 30.0, 0.9])
    model.enrich(theta)
    for j, case in enumerate(model.cases):
        full = cost.solver.linear_solve(
            j, None, case.unit.at(theta), cost.solver.loads(j), rtol=1e-12
        )[case.free].ravel()
        assert np.abs(case.linear(theta) - full).max() < 10 * RTOL * np.abs(full).max()


def test_the_chain_hands_its_equilibria_and_stage_two_validates_beside_the_search():
    """A families+volume chain returns the static equilibria at its answer (kept out of its
    JSON): they are the equilibria a fresh solver finds there. Stage 2 started from them
    takes no Newton step at the chain's answer, and its validation, solved on a thread beside
    the d search, is what finalize would have solved itself, to the bit."""
    from fpm.fitting.calibration import finalize
    from fpm.fitting.damping_stage import fit_damping
    from fpm.fitting.stiffness_stage import ChainResult, run_chain
    from fpm.fitting.validation import validate

    spec = box_spec(
        (5, 4, 6), 0.01,
        forces=[{"at": [0.02, 0.01, 0.05], "vector": [0.0, 0.0, -0.01]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["load_cases"].append({"forces": [{"at": [0.04, 0.03, 0.05], "vector": [0.01, 0, 0]}]})
    spec["validation_cases"] = [{"forces": [{"at": [0.0, 0.0, 0.05], "vector": [0, 0.01, 0]}]}]
    spec["material"]["poisson_ratio"] = 0.45
    spec["annealing"] = {"t_initial": 1.0, "t_final": 0.5, "beta": 1.0}
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    chain = run_chain(problem, reference, 0)
    assert chain.equilibria is not None and chain.equilibria.shape == (2, problem.n_nodes, 3)
    assert "equilibria" not in chain.to_dict()
    assert ChainResult.from_dict(chain.to_dict()).equilibria is None
    fresh = StaticCost(problem, reference.displacements[:2], None)
    for j, u in enumerate(chain.equilibria):
        solved = fresh.displacements(chain.x, j).displacements
        assert np.abs(solved - u).max() < 1e-4 * np.abs(u).max()
    seeded = StaticCost(problem, reference.displacements[:2], None)
    for j, u in enumerate(chain.equilibria):
        seeded.solver.seed(j, model_stiffness(problem, chain.x), None, u)
        again = seeded.displacements(chain.x, j)
        assert again.iterations == 0 and np.array_equal(again.displacements, u)
    stage = fit_damping(problem, reference, [chain])
    assert stage.validation is not None
    checked = None if stage.depth >= stage.full_depth else stage.depth
    alone = validate(problem, reference, stage.theta, checked)
    assert stage.validation["depth"] == checked
    assert stage.validation["relative"] == alone.relative
    result = finalize(problem, reference, [chain], stage)
    assert result.validation_relative_discrepancy == alone.relative
