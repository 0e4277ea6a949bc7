"""The neo-Hookean FEM reference against mathematics: the tangent against finite
differences, the linear limit, the closed-form uniaxial stretch, Newton's quadratic
convergence, independence of the load steps; and its place in the spec, the FEM reference's
identity, its report and its failures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.optimize import brentq

import fpm
from fpm.fem import hyperelastic
from fpm.fem.assembly import stiffness_matrix
from fpm.fem.elasticity import constitutive_matrix
from fpm.fem.hyperelastic import NeoHookeanSolid, NewtonError, solve_hyperelastic
from fpm.fem.neo_hookean import (
    CompressibleNeoHookean,
    MeanDilatationNeoHookean,
    NeoHookeanLaw,
    kinematics,
    neo_hookean_law,
    reference_gradients,
)
from fpm.fem.reference import FemError, FemResult, solve_fem
from fpm.model.geometry import box_hexahedra
from fpm.model.spec import lame_constants
from store.hashing import fem_hash, spec_hash

PAPER_A = Path(__file__).resolve().parents[2] / "examples" / "paper-material-a.json"
E, NU = 1e4, 0.45
MU, LAM = lame_constants(E, NU)
FULL = CompressibleNeoHookean(MU, LAM)
SELECTIVE = neo_hookean_law(MU, LAM, "selective")
LAWS = pytest.mark.parametrize("law", [FULL, SELECTIVE], ids=["full", "selective"])


def paper_spec(model: str = "neo-hookean", scale: float = 1.0) -> dict[str, Any]:
    """The paper's cube, material A (forces 0.25, 0.5, 1 N per pulled node) times ``scale``."""
    spec = json.loads(PAPER_A.read_text())
    spec["material"]["model"] = model
    for case in spec["load_cases"]:
        for force in case["forces"]:
            force["vector"] = [scale * v for v in force["vector"]]
    return spec


def lattice(shape: tuple[int, int, int], size: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) nodes of a box lattice, x fastest (the order of fpm.model.geometry)."""
    axes = [np.linspace(0, s, n) for s, n in zip(size, shape, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def end_face_weights(shape: tuple[int, int, int], size: tuple[float, float, float]) -> np.ndarray:
    """(N,) consistent nodal areas, m^2, of the face x = size[0]: a uniform traction p on the
    bilinear face gives node i the force p * weight_i."""
    factors = []
    for a in range(3):
        n, h = shape[a], size[a] / (shape[a] - 1)
        w = np.full(n, h)
        w[[0, -1]] = h / 2
        if a == 0:
            w = np.zeros(n)
            w[-1] = 1.0
        factors.append(w)
    return np.einsum("k,j,i->kji", factors[2], factors[1], factors[0]).ravel()


# --- the discretisation -----------------------------------------------------------------------


@LAWS
def test_tangent_matches_finite_differences_of_the_residual(law: NeoHookeanLaw):
    """A distorted mesh, a large rotation plus random strains: K = dR/du to 1e-6 relative."""
    shape = (4, 3, 3)
    nodes = lattice(shape, (0.03, 0.02, 0.02))
    rng = np.random.default_rng(3)
    inside = np.all((nodes > 1e-9) & (nodes < nodes.max(axis=0) - 1e-9), axis=1)
    nodes[inside] += rng.uniform(-0.002, 0.002, (int(inside.sum()), 3))
    free = np.ones_like(nodes, dtype=bool)
    free[nodes[:, 2] < 1e-9] = False
    solid = NeoHookeanSolid(nodes, box_hexahedra(shape), law, free, "direct")
    angle = 0.6
    rotation = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    u = nodes @ (rotation.T - np.eye(3)) + 0.001 * rng.standard_normal(nodes.shape)
    k = solid.tangent(u).toarray()
    load = np.zeros_like(nodes)
    eps = 1e-7
    fd = np.empty_like(k)
    for column, unknown in enumerate(np.flatnonzero(free.ravel())):
        plus, minus = u.copy().ravel(), u.copy().ravel()
        plus[unknown] += eps
        minus[unknown] -= eps
        r_plus = solid.residual(plus.reshape(-1, 3), load)[0]
        r_minus = solid.residual(minus.reshape(-1, 3), load)[0]
        fd[:, column] = (r_plus - r_minus) / (2 * eps)
    error = np.linalg.norm(k - fd) / np.linalg.norm(k)
    assert error < 1e-6, error
    assert np.abs(k - k.T).max() <= 1e-12 * np.abs(k).max()  # hyperelastic: symmetric


@LAWS
def test_each_laws_forces_are_the_gradient_of_its_element_energies(law: NeoHookeanLaw):
    """law.forces = d(sum of law.energy)/du on a distorted mesh at a large rotation plus strain
    (full: W at every Gauss point; mean dilatation: isochoric energy at the Gauss points, volume
    energy per element)."""
    shape = (3, 3, 2)
    nodes = lattice(shape, (0.02, 0.02, 0.01))
    rng = np.random.default_rng(7)
    inside = np.all((nodes > 1e-9) & (nodes < nodes.max(axis=0) - 1e-9), axis=1)
    nodes[inside] += rng.uniform(-0.002, 0.002, (int(inside.sum()), 3))
    ref = reference_gradients(nodes, box_hexahedra(shape))
    rotation = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    u = nodes @ (rotation.T - np.eye(3)) + 0.001 * rng.standard_normal(nodes.shape)
    forces = law.forces(ref, kinematics(ref, u), len(nodes))
    eps = 1e-8
    fd = np.empty_like(u)
    for index in np.ndindex(u.shape):
        plus, minus = u.copy(), u.copy()
        plus[index] += eps
        minus[index] -= eps
        fd[index] = (
            law.energy(ref, kinematics(ref, plus)).sum()
            - law.energy(ref, kinematics(ref, minus)).sum()
        ) / (2 * eps)
    assert np.abs(fd - forces).max() <= 1e-6 * np.abs(forces).max()
    rigid = nodes @ (rotation.T - np.eye(3))  # a rigid rotation stores no energy, exerts no force
    assert np.abs(law.energy(ref, kinematics(ref, rigid))).max() <= 1e-12 * MU * 1e-6
    assert (
        np.abs(law.forces(ref, kinematics(ref, rigid), len(nodes))).max()
        <= 1e-9 * np.abs(forces).max()
    )


@pytest.mark.parametrize("integration", ["full", "selective"])
def test_tangent_at_rest_is_the_linear_stiffness_of_the_same_integration(integration: str):
    """At rest each law's tangent is the linear element's: full C at 2x2x2 points, or B-bar."""
    shape = (3, 4, 3)
    nodes = lattice(shape, (0.02, 0.03, 0.025))
    nodes[nodes[:, 0] > 0.015, 2] *= 1.2  # not parallelepipeds: B-bar's mean dilatation matters
    hexahedra = box_hexahedra(shape)
    free = np.ones(3 * len(nodes), dtype=bool)
    law = neo_hookean_law(MU, LAM, integration)
    nh = NeoHookeanSolid(nodes, hexahedra, law, free, "direct").tangent(np.zeros_like(nodes))
    linear = stiffness_matrix(nodes, hexahedra, constitutive_matrix(E, NU), integration)
    assert np.abs((nh - linear).toarray()).max() <= 1e-12 * np.abs(linear.toarray()).max()


@pytest.mark.parametrize("integration", ["full", "selective"])
def test_small_loads_give_the_linear_answer_to_first_order(integration: str):
    """The paper's cube at 1e-3 of its forces: the neo-Hookean and linear answers of the same
    integration differ by far less than 1e-3 (relative), and the difference grows in proportion
    to the load. (Selective: so the neo-Hookean reference no longer locks, as B-bar does not.)"""

    def spec(model: str) -> dict[str, Any]:
        return {**paper_spec(model, 1e-3), "reference": {"integration": integration}}

    linear = solve_fem(fpm.load_problem(spec("linear"))).displacements
    nh = solve_fem(fpm.load_problem(spec("neo-hookean"))).displacements
    forces = np.array([0.25, 0.5, 1.0]) * 1e-3  # N per pulled node
    difference = np.abs(nh - linear).max(axis=(1, 2)) / np.abs(linear).max(axis=(1, 2))
    assert difference.max() < 1e-3, difference
    per_newton = difference / forces  # proportional to the load: constant
    assert np.ptp(per_newton) < 0.01 * per_newton.mean(), per_newton


def uniaxial_bar(
    stretch: float, law: NeoHookeanLaw
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A 0.3 x 0.1 x 0.1 m bar on symmetry rollers (x = 0, y = 0, z = 0 faces each held in
    their normal direction only; the faces y = b and z = b free), a uniform dead traction on
    x = L. Returns nodes, free (N, 3), nodal forces (N, 3) and the exact lateral stretch.

    Closed form: F = diag(s, t, t), J = s t^2. Compressible (full):
    P = mu (F - F^-T) + lambda ln J F^-T; mean dilatation (selective; the deformation is
    homogeneous, so Jbar = J): P = mu J^(-2/3) (F - I1/3 F^-T) + K ln J F^-T, I1 = s^2 + 2 t^2.
    Free lateral faces, P_22(t) = 0, solved for t (1-D); then the nominal traction P_11.
    """

    def piola(s: float, t: float) -> tuple[float, float]:
        """(P_11, P_22) of F = diag(s, t, t)."""
        j = s * t * t
        if isinstance(law, MeanDilatationNeoHookean):
            c, i1 = law.mu * j ** (-2 / 3), s * s + 2 * t * t
            return (
                c * (s - i1 / (3 * s)) + law.bulk * np.log(j) / s,
                c * (t - i1 / (3 * t)) + law.bulk * np.log(j) / t,
            )
        return (
            (law.mu * (s * s - 1) + law.lam * np.log(j)) / s,
            (law.mu * (t * t - 1) + law.lam * np.log(j)) / t,
        )

    shape, size = (7, 3, 3), (0.3, 0.1, 0.1)
    nodes = lattice(shape, size)
    lateral = brentq(lambda t: piola(stretch, t)[1], 1e-3, 10.0)
    traction = piola(stretch, lateral)[0]
    forces = np.zeros_like(nodes)
    forces[:, 0] = traction * end_face_weights(shape, size)
    free = np.ones_like(nodes, dtype=bool)
    for axis in range(3):
        free[nodes[:, axis] < 1e-12, axis] = False
    return nodes, free, forces, lateral


@LAWS
@pytest.mark.parametrize("stretch", [1.5, 0.75])
def test_uniaxial_stretch_of_a_bar_matches_the_closed_form(stretch: float, law: NeoHookeanLaw):
    nodes, free, forces, lateral = uniaxial_bar(stretch, law)
    u, paths = solve_hyperelastic(
        nodes, box_hexahedra((7, 3, 3)), law, forces[None], free, "direct"
    )
    exact = nodes * (np.array([stretch, lateral, lateral]) - 1)
    assert np.abs(u[0] - exact).max() <= 1e-9 * np.abs(exact).max()
    assert paths[0].residual <= hyperelastic.NEWTON_TOLERANCE
    if stretch > 1 and law is FULL:  # the lateral contraction of a stretched nu = 0.45 solid
        assert lateral == pytest.approx(0.8307, abs=1e-4)


def test_newton_converges_quadratically():
    """The paper's cube at 1 N per pulled node in one load step (sparse LU: exact steps)."""
    problem = fpm.load_problem(paper_spec())
    forces = problem.load_cases[2].dense(problem.n_nodes)
    free = np.repeat(~problem.fixed, 3)
    hexahedra = problem.solid.elements()
    _, paths = solve_hyperelastic(problem.nodes, hexahedra, FULL, forces[None], free, "direct")
    history = paths[0].residual_history[0]
    print("||R|| / ||f|| per Newton iteration:", " ".join(f"{r:.3g}" for r in history))
    assert paths[0].load_steps == 1 and history[-1] <= hyperelastic.NEWTON_TOLERANCE
    close = [(a, b) for a, b in zip(history, history[1:], strict=False) if a < 1e-2]
    assert len(close) >= 2
    for before, after in close:  # r_{k+1} <= C r_k^2
        assert after <= 5.0 * before**2, history


def test_the_answer_does_not_depend_on_the_load_steps():
    problem = fpm.load_problem(paper_spec())
    forces = problem.load_cases[2].dense(problem.n_nodes)[None]
    free = np.repeat(~problem.fixed, 3)
    hexahedra = problem.solid.elements()
    answers = {}
    for steps in (1, 4):
        u, paths = solve_hyperelastic(
            problem.nodes, hexahedra, FULL, forces, free, "direct", load_steps=steps
        )
        assert paths[0].load_steps == steps and paths[0].load_factors[-1] == 1.0
        answers[steps] = u[0]
    scale = np.abs(answers[1]).max()
    for steps in (4,):
        assert np.abs(answers[steps] - answers[1]).max() <= 1e-9 * scale


@pytest.fixture(scope="module")
def paper_reference() -> FemResult:
    """The paper's cube, material A, neo-Hookean, by sparse LU."""
    return solve_fem(fpm.load_problem(paper_spec()), method="direct")


def test_direct_and_multigrid_newton_steps_agree(paper_reference: FemResult):
    amg = solve_fem(fpm.load_problem(paper_spec()), method="amg")
    assert amg.method == "amg" and max(amg.residuals) <= hyperelastic.NEWTON_TOLERANCE
    scale = np.abs(paper_reference.displacements).max()
    assert np.abs(amg.displacements - paper_reference.displacements).max() <= 1e-8 * scale


def test_large_loads_move_the_pulled_nodes_further_than_the_linear_answer(
    paper_reference: FemResult,
):
    """At 1 N per pulled node the cube is outside small strain: the pulled nodes stretch
    their hexahedra by more than h, and the neo-Hookean answer is 19% further."""
    linear = solve_fem(fpm.load_problem(paper_spec("linear"))).displacements
    ratio = np.abs(paper_reference.displacements).max(axis=(1, 2)) / np.abs(linear).max(axis=(1, 2))
    assert np.all(np.diff(ratio) > 0) and 1.1 < ratio[2] < 1.3, ratio


# --- the reference: report, identity, failures ------------------------------------------------


def test_the_reference_reports_its_load_steps_newton_iterations_and_residuals():
    result = solve_fem(fpm.load_problem(small_box()), load_steps=2)
    assert result.model == "neo-hookean" and result.load_cases == ["pull", "push"]
    assert result.load_steps == [2, 2]
    assert all(len(steps) == 2 and min(steps) >= 1 for steps in result.newton_iterations)
    assert max(result.residuals) <= hyperelastic.NEWTON_TOLERANCE
    back = FemResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert back.model == "neo-hookean" and back.load_steps == result.load_steps
    assert back.newton_iterations == result.newton_iterations
    assert np.array_equal(back.displacements, result.displacements)
    linear = solve_fem(fpm.load_problem(small_box("linear")))
    assert linear.model == "linear" and linear.load_steps == [] == linear.newton_iterations


def test_a_reference_stored_before_the_model_field_reads_as_linear():
    data = solve_fem(fpm.load_problem(paper_spec("linear", 0.1))).to_dict()
    for key in ("model", "load_steps", "newton_iterations"):
        del data[key]
    old = FemResult.from_dict(data)
    assert old.model == "linear" and old.load_steps == [] and old.newton_iterations == []


def test_the_model_is_a_validated_spec_field():
    default = fpm.ProblemSpec.model_validate(paper_spec("linear"))
    assert default.material.model == "linear"
    with pytest.raises(ValidationError) as caught:
        fpm.ProblemSpec.model_validate(paper_spec("mooney-rivlin"))
    error = caught.value.errors()[0]
    assert error["loc"] == ("material", "model")
    assert "'linear' or 'neo-hookean'" in error["msg"]


def test_the_model_is_part_of_the_references_identity_and_linear_keys_are_unchanged():
    """The FEM hash covers the material, so the model is in the key; "linear" (the default) is
    left out of dumps, so a linear spec keeps the hash it had before the field existed."""
    before = json.loads(PAPER_A.read_text())  # no model field, as stored specs were
    explicit = paper_spec("linear")
    nh = paper_spec("neo-hookean")
    dump = {
        name: fpm.ProblemSpec.model_validate(s).model_dump(mode="json")
        for name, s in (("before", before), ("explicit", explicit), ("nh", nh))
    }
    assert "model" not in dump["explicit"]["material"]
    assert dump["nh"]["material"]["model"] == "neo-hookean"
    assert fem_hash(dump["explicit"]) == fem_hash(dump["before"])
    assert spec_hash(dump["explicit"]) == spec_hash(dump["before"])
    assert fem_hash(dump["nh"]) != fem_hash(dump["before"])
    assert spec_hash(dump["nh"]) != spec_hash(dump["before"])
    assert fpm.ProblemSpec.model_validate(dump["nh"]).material.model == "neo-hookean"


def small_box(model: str = "neo-hookean", force: float = 0.05) -> dict[str, Any]:
    return {
        "name": "small box",
        "material": {"youngs_modulus": E, "poisson_ratio": NU, "density": 1040.0, "model": model},
        "geometry": {"type": "box", "size": [0.04, 0.04, 0.04], "nodes": [5, 5, 5]},
        "fixed": [{"face": "z-"}],
        "load_cases": [
            {"name": "pull", "forces": [{"at": [0.02, 0.02, 0.04], "vector": [0, 0, force]}]},
            {"name": "push", "forces": [{"at": [0.02, 0.02, 0.04], "vector": [0, 0, -force]}]},
        ],
        "fpm": {"depth": 10},
    }


def test_newton_that_does_not_converge_fails_clearly_naming_the_load_step(monkeypatch):
    monkeypatch.setattr(hyperelastic, "MAX_NEWTON_ITERATIONS", 2)
    monkeypatch.setattr(hyperelastic, "MAX_STEP_HALVINGS", 1)
    with pytest.raises(NewtonError) as caught:
        solve_fem(fpm.load_problem(small_box()))
    message = str(caught.value)
    assert "load case 'pull'" in message and "load step 1 (load factor 0 -> 0.5" in message
    assert "after 2 Newton iterations" in message and "lower the forces" in message
    assert isinstance(caught.value, FemError)  # the worker fails the reference with it


def test_an_inverted_hexahedron_is_named(monkeypatch):
    """Only the full Newton step is tried: its first (linear) step pushes the loaded node
    through the hexahedron below it."""
    monkeypatch.setattr(hyperelastic, "LINE_SEARCH_HALVINGS", 0)
    monkeypatch.setattr(hyperelastic, "MAX_STEP_HALVINGS", 0)
    spec = small_box(force=5.0)
    spec["load_cases"] = spec["load_cases"][1:]
    with pytest.raises(NewtonError, match=r"load case 'push'.*load step 1 .*hexahedron \d+ "):
        solve_fem(fpm.load_problem(spec))


@pytest.mark.parametrize(
    ("integration", "why"),
    [
        ("full", r"more than 10 times the solid's size"),
        ("selective", r"the residual does not decrease along the Newton step"),
    ],
)
def test_a_units_slip_fails_fast_instead_of_following_the_solid_away(integration: str, why: str):
    """E = 10 Pa for 10 kPa: no equilibrium within ten times the solid's size (full); the
    mean-dilatation elements fail earlier (about 5% of the load: no decrease along the step)."""
    spec = {**small_box(), "reference": {"integration": integration}}
    spec["material"]["youngs_modulus"] = 10.0
    with pytest.raises(NewtonError, match=why + r".*check the units") as caught:
        solve_fem(fpm.load_problem(spec))
    assert (hyperelastic.SELECTIVE_HINT in str(caught.value)) == (integration == "selective")


def test_check_reference_drops_the_small_strain_warning_but_keeps_the_units_error(
    paper_reference: FemResult,
):
    from fpm.fitting.diagnosis import UnitsError, check_reference

    nh, linear = fpm.load_problem(paper_spec()), fpm.load_problem(paper_spec("linear"))
    assert check_reference(nh, paper_reference) == []  # pulled nodes 1.7 h: no warning
    assert len(check_reference(linear, paper_reference)) == 1  # "outside small strain"
    with pytest.raises(UnitsError, match="the neo-Hookean FEM reference moves node"):
        check_reference(nh, 10 * paper_reference.displacements)


def test_calibration_runs_against_the_neo_hookean_reference():
    problem = fpm.load_problem(small_box(force=0.02))
    reference = solve_fem(problem)
    result = fpm.calibrate(problem, reference=reference, threads=1)
    assert result.parameters.k > 0 and len(result.fit.relative_discrepancy) == 2
    linear = fpm.calibrate(fpm.load_problem(small_box("linear", 0.02)), threads=1)
    assert result.parameters.k != linear.parameters.k  # a different reference, a different fit
