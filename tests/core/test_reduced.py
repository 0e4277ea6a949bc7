"""Stage 1's reduced linear model (fpm.fitting.reduced) against mathematics: the lattice's
stiffness at rest is linear in the fitted parameters (the shared-pattern K(theta) is the
tangent assembled at theta), and the reduced model is exact on a basis that holds the exact
response (Galerkin). And its place in a calibration: the first basis built once and handed to
the chains gives the same bits as a chain that builds it, a chain given it makes no full
solve, the defect-corrected fit runs once per calibration (the damping stage's polish)."""

from __future__ import annotations

import numpy as np
from helpers_fpm import box_spec

import fpm
from fpm.dynamics.equilibrium import StaticSolver
from fpm.fitting.cost import StaticCost
from fpm.fitting.reduced import RTOL, ReducedBasis, ReducedLinearModel, first_basis
from fpm.fitting.unit_matrices import unit_matrices
from fpm.model.stiffness import (
    continuum_start,
    family_names,
    fitted_theta,
    linear_parts,
    model_stiffness,
)


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
    system, _ = cost.solver.system(0, None)
    units = unit_matrices(problem, system, linear_parts(problem)[0], None)
    direct = system.tangent(np.zeros((system.n_free, 3)), system.parameters(
        model_stiffness(problem, theta)), modified=True)  # fmt: skip
    combined = units.at(theta)
    scale = np.abs(direct.toarray()).max()
    assert np.abs((combined - direct).toarray()).max() < 1e-12 * scale
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
    model = ReducedLinearModel.of(problem, first_basis(problem), cost.reference)
    model.attach([cost.solver] * len(model.cases), None)
    theta = np.array(start) * np.array([0.8, 1.2, 30.0, 0.9])
    model.enrich(theta)
    for j, case in enumerate(model.cases):
        full = cost.solver.linear_solve(
            j, None, case.unit.at(theta), cost.solver.loads(j), rtol=1e-12
        )[case.free].ravel()
        assert np.abs(case.linear(theta) - full).max() < 10 * RTOL * np.abs(full).max()


def small_fit(validation: bool = True, short: bool = True) -> tuple[fpm.Problem, object]:
    """The 5x4x6 box (families+volume, two load cases, a validation case), with a short
    schedule (else the default: 15 moves), and its FEM reference."""
    spec = box_spec(
        (5, 4, 6), 0.01,
        forces=[{"at": [0.02, 0.01, 0.05], "vector": [0.0, 0.0, -0.01]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["load_cases"].append({"forces": [{"at": [0.04, 0.03, 0.05], "vector": [0.01, 0, 0]}]})
    if validation:
        spec["validation_cases"] = [{"forces": [{"at": [0.0, 0.0, 0.05], "vector": [0, 0.01, 0]}]}]
    spec["material"]["poisson_ratio"] = 0.45
    if short:
        spec["annealing"] = {"t_initial": 1.0, "t_final": 0.5, "beta": 1.0}
    problem = fpm.load_problem(spec)
    return problem, fpm.solve_fem(problem)


class CountedSolves:
    """Counts StaticSolver.linear_solve calls (full solves and V-cycles) while active."""

    def __init__(self, monkeypatch):
        self.calls = 0
        real = StaticSolver.linear_solve

        def counted(solver, *args, **kwargs):
            self.calls += 1
            return real(solver, *args, **kwargs)

        monkeypatch.setattr(StaticSolver, "linear_solve", counted)


def test_a_chain_on_the_stored_basis_equals_one_that_builds_it_and_makes_no_solve(monkeypatch):
    """The first basis through its stored form (raw arrays, as Redis holds it) gives a chain
    the same moves, answer and cost to the bit as a chain that builds the basis itself; the
    chain given it makes no linear solve at all, where building it takes one full solve and
    one V-cycle per parameter for each load case. A chain resumed from a checkpoint on it ends
    where the uninterrupted one does (the resumed chain anneals the same reduced model)."""
    from fpm.fitting.stiffness_stage import run_chain

    problem, reference = small_fit(short=False)
    counter = CountedSolves(monkeypatch)
    built = run_chain(problem, reference, 0)
    n_params, n_cases = len(family_names(problem)), len(problem.load_cases)
    assert counter.calls == n_cases * (1 + n_params)
    basis = first_basis(problem)
    assert basis.solves == n_cases
    stored = ReducedBasis.from_stored(*basis.to_stored())
    for a, b in zip(basis.cases, stored.cases, strict=True):
        for x, y in ((a.free, b.free), (a.basis, b.basis), (a.projected, b.projected),
                     (a.rhs, b.rhs)):  # fmt: skip
            assert x.dtype == y.dtype and np.array_equal(x, y)
    counter.calls = 0
    checkpoints = []
    given = run_chain(problem, reference, 0, basis=stored, checkpoint=checkpoints.append)
    assert counter.calls == 0
    assert given.x == built.x and given.cost == built.cost and given.history == built.history
    assert checkpoints
    resumed = run_chain(problem, reference, 0, basis=stored, resume=checkpoints[0])
    assert (resumed.x, resumed.cost, resumed.history) == (given.x, given.cost, given.history)


def test_the_defect_corrected_fit_runs_once_per_calibration(monkeypatch):
    """Two chains anneal; the defect-corrected fit runs once, from the best chain's state, in
    the damping stage, and a static solve at its answer then takes no Newton step (its last
    round's equilibria are the solver's warm starts). The stage given the first basis lands
    on the same parameters to the bit as one that builds it, and as calibrate."""
    import fpm.fitting.damping.polish as damping_stage
    from fpm.fitting.bounds import stiffness_bounds
    from fpm.fitting.calibration import calibrate
    from fpm.fitting.damping.stage import fit_stage as fit_damping
    from fpm.fitting.defect_correction import fit_reduced
    from fpm.fitting.stiffness_stage import run_chain

    problem, reference = small_fit(validation=False)
    starts = []

    def counted_fit(*args, **kwargs):
        starts.append(args[2])
        return fit_reduced(*args, **kwargs)

    monkeypatch.setattr(damping_stage, "fit_reduced", counted_fit)
    result = calibrate(problem, reference=reference, chains=2, threads=1)
    assert len(starts) == 1
    assert starts[0] == min(result.run.chains, key=lambda c: c.cost).x
    chains = [run_chain(problem, reference, c) for c in range(2)]
    stage = fit_damping(problem, reference, chains)
    given = fit_damping(problem, reference, chains, basis=first_basis(problem))
    assert stage.theta == given.theta == fitted_theta(problem, result.parameters)
    cost = StaticCost(problem, reference.displacements[:2], None)
    theta, _, _ = fit_reduced(cost, first_basis(problem), starts[0], stiffness_bounds(problem))
    assert theta == stage.theta
    assert [cost.displacements(theta, j).iterations for j in range(2)] == [0, 0]


def test_the_fit_is_the_same_on_one_or_two_threads():
    """Three load cases over the fit's two static solvers (one: every linear response and
    case 0's equilibrium, the other: cases 1 and 2's): the same answer to the bit whether the
    two solvers' shares run one after the other or at once, and every case's equilibrium at
    the answer is a warm start of the cost's solver."""
    from fpm.fitting.bounds import stiffness_bounds
    from fpm.fitting.defect_correction import fit_reduced

    spec = box_spec(
        (5, 4, 6), 0.01,
        forces=[{"at": [0.02, 0.01, 0.05], "vector": [0.0, 0.0, -0.01]}],
        fpm_settings={"stiffness": "families+volume"},
    )  # fmt: skip
    spec["load_cases"] += [
        {"forces": [{"at": [0.04, 0.03, 0.05], "vector": [0.01, 0, 0]}]},
        {"forces": [{"at": [0.0, 0.0, 0.05], "vector": [0, 0.01, 0]}]},
    ]
    spec["material"]["poisson_ratio"] = 0.45
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem).displacements[:3]
    start = np.array(continuum_start(problem)) * np.array([1.2, 0.8, 20.0, 1.1])
    answers = []
    for threads in (1, 2):
        cost = StaticCost(problem, reference, None)
        answers.append(fit_reduced(cost, first_basis(problem), list(start),
                                   stiffness_bounds(problem), threads=threads))  # fmt: skip
        assert [cost.displacements(answers[-1][0], j).iterations for j in range(3)] == [0, 0, 0]
    assert answers[0] == answers[1]


def test_a_round_without_equilibrium_ends_the_fit_at_the_round_before(monkeypatch):
    """The reduced model can lead where the solid has no static equilibrium; the fit then
    keeps the last round that had one (its parameters and cost, as an uninterrupted fit of
    that many rounds gives them) or, failing in the first round, the start."""
    import dataclasses

    import fpm.fitting.defect_correction as dc
    from fpm.fitting.bounds import stiffness_bounds

    problem, reference = small_fit(validation=False)
    start = list(np.array(continuum_start(problem)) * np.array([1.2, 0.8, 20.0, 1.1]))
    bounds = stiffness_bounds(problem)
    real = dc._solver_round

    def fit(fail_from: int | None, rounds: int = dc.DEFECT_ROUNDS):
        calls = {"n": 0}

        def solver_round(responses, statics, solver, stiffness, depth):
            linear, solved = real(responses, statics, solver, stiffness, depth)
            if responses:  # solver 0: once per round
                calls["n"] += 1
            if fail_from is not None and calls["n"] >= fail_from:
                solved = {j: dataclasses.replace(e, converged=False) for j, e in solved.items()}
            return linear, solved

        monkeypatch.setattr(dc, "_solver_round", solver_round)
        monkeypatch.setattr(dc, "DEFECT_ROUNDS", rounds)
        cost = StaticCost(problem, reference.displacements[:2], None)
        return dc.fit_reduced(cost, first_basis(problem), start, bounds, threads=1)

    theta, static, _ = fit(fail_from=1)
    assert theta == list(np.exp(np.clip(np.log(start), *np.log(bounds))))
    assert static == float("inf")
    one_round = fit(fail_from=None, rounds=1)
    assert one_round[1] < float("inf")
    failed_second = fit(fail_from=2)
    assert failed_second[:2] == one_round[:2]


def test_stage_two_validates_beside_the_search():
    """The validation cases, solved on a thread beside the d search once the polish is done,
    are what finalize would have solved itself, to the bit."""
    from fpm.fitting.calibration import finalize
    from fpm.fitting.damping.stage import fit_stage as fit_damping
    from fpm.fitting.damping.validation import validate
    from fpm.fitting.stiffness_stage import run_chain

    problem, reference = small_fit()
    chain = run_chain(problem, reference, 0)
    stage = fit_damping(problem, reference, [chain])
    assert stage.validation is not None
    checked = None if stage.depth >= stage.full_depth else stage.depth
    alone = validate(problem, reference, stage.theta, checked)
    assert stage.validation["depth"] == checked
    assert stage.validation["relative"] == alone.relative
    result = finalize(problem, reference, [chain], stage)
    assert result.fit.validation_relative_discrepancy == alone.relative
