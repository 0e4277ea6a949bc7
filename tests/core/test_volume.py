"""The volume term and the families+volume model, tested against mathematics: the trilinear
volume and its derivatives, the continuum constants of a block under uniform strain, kappa = 0,
the dynamic kernel against the static equilibrium, inverted cells, and the stability estimate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers_fpm import box_spec

import fpm
from fpm.dynamics.equilibrium import StaticSolver, static_equilibrium
from fpm.dynamics.simulation import FpmModel
from fpm.dynamics.stability import stable_time_step
from fpm.dynamics.voigt import volume_forces as kernel_volume_forces
from fpm.model.forces import Stiffness, cells, internal_energy, internal_forces
from fpm.model.geometry import hexahedron_volumes
from fpm.model.hexahedron import NATURAL
from fpm.model.spec import lame_constants
from fpm.model.stiffness import (
    assembly_weights,
    continuum_start,
    family_names,
    model_stiffness,
    spring_stiffness,
    theta_of,
)
from fpm.model.volume import (
    COEFFICIENTS,
    Cells,
    coefficient_gradient,
    coefficient_hessian,
    volume_energy,
    volume_forces,
)

VOLUME_MODE = {"stiffness": "families+volume", "dt": 1e-3}


def distorted_cell(seed: int) -> np.ndarray:
    """(8, 3) corners of a brick 1 x 2 x 3 mm with every corner moved by up to 10%."""
    rng = np.random.default_rng(seed)
    return 1e-3 * ((NATURAL + 1) / 2 * [1.0, 2.0, 3.0] + 0.1 * rng.standard_normal((8, 3)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_closed_form_volume_is_the_quadrature_volume(seed: int):
    """V = 8 [a1,a2,a3] + 8/3 (...) equals 2x2x2 Gauss quadrature of det J (exact for trilinear
    maps), at rest and deformed; V - V0 is computed without cancellation."""
    x = distorted_cell(seed)
    one = np.arange(8)[None]
    c = Cells.from_hexahedra(x, one)
    assert c.volume[0] == pytest.approx(hexahedron_volumes(x, one)[0], rel=1e-13)
    u = 1e-4 * np.random.default_rng(seed + 10).standard_normal((8, 3))
    from fpm.model.volume import cell_volumes

    change = cell_volumes(c, u)[0]
    assert change == pytest.approx(
        hexahedron_volumes(x + u, one)[0] - hexahedron_volumes(x, one)[0], rel=1e-9
    )
    tiny = 1e-12 * u  # where V' - V would lose every digit to cancellation
    assert cell_volumes(c, tiny)[0] == pytest.approx(1e-12 * change, rel=1e-6)


def test_volume_forces_are_minus_the_energy_gradient():
    x = distorted_cell(3)
    c = Cells.from_hexahedra(x, np.arange(8)[None])
    kappa = np.array([4e3])
    u = 2e-4 * np.random.default_rng(4).standard_normal((8, 3))
    forces = volume_forces(c, kappa, u)
    eps = 1e-9
    numeric = np.zeros_like(u)
    for n in range(8):
        for d in range(3):
            step = np.zeros_like(u)
            step[n, d] = eps
            numeric[n, d] = (
                volume_energy(c, kappa, u + step) - volume_energy(c, kappa, u - step)
            ) / (2 * eps)
    assert forces == pytest.approx(-numeric, rel=1e-5, abs=1e-7 * np.abs(forces).max())


def test_the_coefficient_hessian_is_the_derivative_of_the_gradient():
    x = distorted_cell(5)
    a = np.einsum("kn,nd->kd", COEFFICIENTS, x)
    hessian = np.empty((6, 6, 3, 3))
    coefficient_hessian(a, hessian)
    eps = 1e-9
    for k in range(6):
        for d in range(3):
            up, down = a.copy(), a.copy()
            up[k, d] += eps
            down[k, d] -= eps
            gu, gd = np.empty((6, 3)), np.empty((6, 3))
            coefficient_gradient(up, gu)
            coefficient_gradient(down, gd)
            numeric = (gu - gd) / (2 * eps)
            assert hessian[k, :, d, :] == pytest.approx(numeric, rel=1e-6, abs=1e-12)


def test_the_kernel_volume_forces_equal_the_definition():
    """The dynamic kernel's blocked, written-out formulas equal fpm.model.volume's."""
    problem = fpm.load_problem(box_spec((5, 4, 6), 0.01, fpm_settings=VOLUME_MODE))
    c = cells(problem)
    rng = np.random.default_rng(6)
    kappa = rng.uniform(1e3, 1e4, len(c.volume))
    u = rng.normal(0, 1e-3, (problem.n_nodes, 3))
    out = np.zeros_like(u)
    inverted = kernel_volume_forces(
        c.corners, c.rest, c.volume, kappa, problem.nodes + u, np.arange(problem.n_nodes), out
    )
    assert inverted == -1
    expected = volume_forces(c, kappa, u)
    assert out == pytest.approx(expected, rel=1e-9, abs=1e-12 * np.abs(expected).max())


def strain_energy_density(problem: fpm.Problem, stiffness: Stiffness, strain: np.ndarray) -> float:
    """Energy per volume, J/m^3, of the block under the uniform small ``strain`` (3, 3)."""
    u = problem.nodes @ strain.T
    volume = float(np.prod(np.ptp(problem.nodes, axis=0)))
    return internal_energy(problem, stiffness, u) / volume


def test_a_block_under_uniform_strain_has_the_closed_form_constants():
    """Springs assembled from cells plus the volume term: under any uniform strain the whole
    block (surface included) stores exactly the continuum energy of C11 = (k1 + 2 k2 +
    4 k3 / 3) / h + kappa, C12 = (k2 + 4 k3 / 3) / h + kappa, C44 = (k2 + 4 k3 / 3) / h."""
    h = 0.01
    problem = fpm.load_problem(box_spec((4, 5, 3), h, fpm_settings=VOLUME_MODE))
    k1, k2, k3, kappa = 30.0, 20.0, 6.0, 5e3
    stiffness = model_stiffness(problem, [k1, k2, k3, kappa])
    c11 = (k1 + 2 * k2 + 4 * k3 / 3) / h + kappa
    c12 = (k2 + 4 * k3 / 3) / h + kappa
    c44 = (k2 + 4 * k3 / 3) / h
    e = 1e-7
    cases = {
        "uniaxial": (np.diag([e, 0, 0]), 0.5 * c11 * e * e),
        "biaxial": (np.diag([e, e, 0]), (c11 + c12) * e * e),
        "shear": (np.array([[0, e, 0], [e, 0, 0], [0, 0, 0]]), 0.5 * c44 * (2 * e) ** 2),
    }
    for strain, expected in cases.values():
        assert strain_energy_density(problem, stiffness, strain) == pytest.approx(
            expected, rel=1e-5
        )


def test_the_continuum_start_is_the_material_in_the_interior():
    """k1 = k2 = mu h, k3 = 0, kappa = lambda - mu give C11 = lambda + 2 mu, C12 = lambda,
    C44 = mu (k3 sits at its tiny floor)."""
    problem = fpm.load_problem(box_spec((4, 4, 4), 0.01, fpm_settings=VOLUME_MODE))
    mu, lam = lame_constants(1e4, 0.45)
    k1, k2, k3, kappa = continuum_start(problem)
    h = problem.h
    assert k1 == k2 == pytest.approx(mu * h) and k3 < 1e-2 * mu * h
    assert kappa == pytest.approx(lam - mu)
    assert (k1 + 2 * k2 + 4 * k3 / 3) / h + kappa == pytest.approx(lam + 2 * mu, rel=1e-3)
    assert (k2 + 4 * k3 / 3) / h + kappa == pytest.approx(lam, rel=1e-3)
    assert family_names(problem) == ("axis", "face", "body", "kappa")


def test_assembled_springs_are_softer_on_the_surface():
    """An interior spring gets its family's k (4 cells x 1/4, 2 x 1/2, 1 x 1); a spring on a
    face half of it, on an edge of the block a quarter."""
    problem = fpm.load_problem(box_spec((4, 4, 4), 0.01, fpm_settings=VOLUME_MODE))
    w = assembly_weights(problem)
    s = problem.solid.springs
    mid = problem.nodes[s].mean(axis=1)
    lo, hi = problem.nodes.min(axis=0), problem.nodes.max(axis=0)
    on_faces = ((np.abs(mid - lo) < 1e-9) | (np.abs(mid - hi) < 1e-9)).sum(axis=1)
    assert np.all(w[on_faces == 0] == 1.0)
    edges = problem.solid.families == 0
    assert np.all(w[edges & (on_faces == 1)] == 0.5)
    assert np.all(w[edges & (on_faces == 2)] == 0.25)
    assert np.all(w[(problem.solid.families == 1) & (on_faces == 1)] == 0.5)


def test_kappa_zero_is_the_spring_model_exactly():
    """A volume term with kappa = 0 changes nothing: the same static equilibrium and the same
    dynamic run, bit for bit, as the same springs alone."""
    problem = fpm.load_problem(box_spec((4, 4, 5), 0.01, fpm_settings=VOLUME_MODE))
    springs_only = fpm.load_problem(
        box_spec((4, 4, 5), 0.01, fpm_settings={"stiffness": "families"})
    )
    springs = spring_stiffness(problem, [20.0, 15.0, 5.0, 1.0])
    zero = Stiffness(springs, np.zeros(len(cells(problem).volume)))
    alone = Stiffness(springs)
    a = StaticSolver(problem, warm=False).solve(0, zero, None)
    b = StaticSolver(springs_only, warm=False).solve(0, alone, None)
    assert np.array_equal(a.displacements, b.displacements) and a.iterations == b.iterations
    run = dict(d=0.05, depth=None, dt=5e-4, max_steps=400, settle_tolerance=0.0)
    x = FpmModel(problem).run(0, k=zero, **run)
    y = FpmModel(springs_only).run(0, k=alone, **run)
    assert np.array_equal(x.displacements, y.displacements)


@pytest.mark.parametrize("force", [0.01, 0.2])
def test_the_dynamic_run_settles_at_the_static_equilibrium(force: float):
    """With the volume term (volume forces once per step, springs node by node) a settled run
    reaches the static equilibrium of springs + volume, small and large (rotating) loads."""
    spec = box_spec(
        (4, 4, 6), 0.01, fpm_settings={**VOLUME_MODE, "dt": "auto", "settle_tolerance": 1e-8,
                                       "max_steps": 100_000},
        forces=[{"at": [0.0, 0.0, 0.05], "vector": [force, 0.0, force]}],
    )  # fmt: skip
    problem = fpm.load_problem(spec)
    theta = continuum_start(problem)
    static = static_equilibrium(problem, k=theta, tolerance=1e-10)
    run = fpm.simulate(problem, k=theta, d=0.3)
    assert run.settled
    scale = np.abs(static.displacements).max()
    assert np.abs(run.displacements - static.displacements).max() < 1e-5 * scale
    # The settled state balances forces by the NumPy definition of the terms too.
    residual = internal_forces(problem, model_stiffness(problem, theta), run.displacements)
    residual += problem.load_cases[0].dense(problem.n_nodes)
    assert np.abs(residual[~problem.fixed]).max() < 1e-6 * force


def test_an_inverted_cell_is_a_clear_error_naming_the_cell_and_the_load_case():
    """A top face crushed by 30 N (each cell 1 cm high, the solid 2 cm): a cell's volume reaches
    zero before any node leaves the solid's size."""
    spec = box_spec(
        (3, 3, 3), 0.01, fpm_settings={**VOLUME_MODE, "dt": 1e-4, "max_steps": 5000},
        forces=[{"face": "z+", "vector": [0.0, 0.0, -30.0], "distribute": True}],
    )  # fmt: skip
    problem = fpm.load_problem(spec)
    run = fpm.simulate(problem, k=continuum_start(problem), d=0.01)
    assert run.diverged and not run.settled and run.inverted_cell is not None
    assert f"cell {run.inverted_cell}" in run.message and "load case 0" in run.message
    assert 0 <= run.inverted_cell < len(problem.solid.elements())


def test_the_stability_estimate_with_the_volume_term():
    """At the continuum start (nu = 0.45) the volume term shortens the estimate by about 1.9x
    on a cube; runs at half the estimate settle, at three times it they diverge."""
    spec = box_spec((6, 6, 6), 0.01, fpm_settings={**VOLUME_MODE, "max_steps": 20000})
    problem = fpm.load_problem(spec)
    theta = continuum_start(problem)
    stiffness = model_stiffness(problem, theta)
    with_volume = stable_time_step(problem, stiffness)
    springs_only = stable_time_step(problem, stiffness.springs)
    assert 1.6 < springs_only / with_volume < 2.2
    m = problem.solid.masses.mean()
    d = 0.5 * np.sqrt(problem.spec.material.youngs_modulus * problem.h * m)
    settles = fpm.simulate(problem, k=theta, d=d, dt=0.5 * with_volume)
    assert settles.settled
    diverges = fpm.simulate(problem, k=theta, d=d, dt=3 * with_volume, max_steps=2000)
    assert diverges.diverged


def test_the_mode_is_refused_where_the_lattice_has_no_cells_or_no_shear():
    from pydantic import ValidationError

    with pytest.raises(ValidationError) as e:
        fpm.load_problem(box_spec((3, 3, 3), connectivity="axis", fpm_settings=VOLUME_MODE))
    assert e.value.errors()[0]["loc"] == ("fpm", "stiffness")
    assert "face diagonals" in e.value.errors()[0]["msg"]
    # Named no mode: the default follows the lattice.
    default = box_spec((3, 3, 3), connectivity="axis")
    default["fpm"] = {}
    assert fpm.load_problem(default).spec.fpm.stiffness == "single"
    default = box_spec((3, 3, 3))
    default["fpm"] = {}
    assert fpm.load_problem(default).spec.fpm.stiffness == "families+volume"
    assert fpm.load_problem(default).spec.fpm.dt == "auto"


PAPER_A = Path(__file__).resolve().parents[2] / "examples" / "paper-material-a.json"


def cube_spec(nu: float, integration: str) -> dict:
    """The paper's cube and forces (material A) with the default model, two validation cases."""
    spec = json.loads(PAPER_A.read_text())
    spec["material"]["poisson_ratio"] = nu
    spec["reference"] = {"integration": integration}
    spec["fpm"] = {"depth": 10}  # the default model, dt auto
    spec["validation_cases"] = [
        {"name": "sideways", "forces": [{"at": [0.0444444444, 0.0444444444, 0.1],
                                         "vector": [0.5, 0, 0]}]},
        {"name": "corner", "forces": [{"at": [0.1, 0.1, 0.1], "vector": [0, 0, -0.5]}]},
    ]  # fmt: skip
    return spec


@pytest.mark.slow
@pytest.mark.parametrize(
    ("nu", "integration", "goal"),
    [(0.45, "full", 5.0), (0.45, "selective", 7.5), (0.49, "selective", 10.0)],
)
def test_the_default_model_is_soft_tissue_on_the_paper_cube(
    nu: float, integration: str, goal: float
):
    """The goal: at nu 0.45 the default model's mean relative discrepancy <= 5% against
    the reference its prototype was measured on (2x2x2, measured 3.8%), 7.5% against the default
    selective one (measured 6.8%); <= 10% at nu 0.49 (measured 6.6%), where one k stays at 21-25%.
    The validation figures are the static equilibria of the validation cases at the fitted
    stiffness, checked here by an independent solve."""
    problem = fpm.load_problem(cube_spec(nu, integration))
    assert problem.spec.fpm.stiffness == "families+volume"
    reference = fpm.solve_fem(problem)
    result = fpm.calibrate(problem, reference=reference)
    assert result.fit.mean_relative_discrepancy <= goal
    assert (
        result.parameters.volume_stiffness is not None
        and result.settle.dt is not None
        and result.settle.dt <= 1e-3
    )
    assert result.fit.validation_cases == ["sideways", "corner"]
    assert len(result.fit.validation_relative_discrepancy) == 2
    assert max(result.fit.validation_relative_discrepancy) < 20.0
    theta = theta_of(
        problem,
        result.parameters.k,
        result.parameters.stiffness,
        result.parameters.volume_stiffness,
    )
    checked = problem.validation_problem()
    truth = reference.displacements[len(problem.load_cases) :]
    for j in range(2):
        u = static_equilibrium(checked, k=theta, load_case=j)
        error = np.linalg.norm(u.displacements - truth[j], axis=1).sum()
        relative = 100 * error / np.linalg.norm(truth[j], axis=1).sum()
        assert relative == pytest.approx(result.fit.validation_relative_discrepancy[j], abs=0.05)
