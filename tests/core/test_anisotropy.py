"""Transversely isotropic material: the FEM (hexahedra, both integrations,
and 10-node tetrahedra) against the analytic uniaxial stretch along and across the axis; the
lattice's closed-form start and its fitted axial scale; the spec's refusals."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from helpers_fpm import box_spec, spec_errors, stage_one

import fpm
from fpm.fem import tet10
from fpm.fem.materials import hexahedron_stiffness, tetrahedron_elasticity
from fpm.fem.solution import solve_dirichlet
from fpm.fitting.cost import StaticCost
from fpm.fitting.reference import reference_displacements
from fpm.model.anisotropy import closed_form_start, lattice_constants
from fpm.model.spec import ReferenceSettings
from fpm.model.stiffness import (
    assembly_weights,
    continuum_start,
    family_names,
    fitted_theta,
    model_stiffness,
    stiffness_dict,
    volume_stiffness,
)
from fpm.model.tetrahedra import TetMesh

AS_GIVEN = {"refine": 0} if "refine" in ReferenceSettings.model_fields else {}
"""reference: the mesh as given (no refinement levels: these tests compare one solve)."""

E_A, E_T, NU_T, NU_A, G_A = 50e3, 10e3, 0.45, 0.3, 8e3
"""A fibre-like solid: 5x stiffer along its axis, Pa."""


def ti(axis=(0.0, 0.0, 1.0), **more) -> dict:
    return {
        "type": "transversely-isotropic",
        "axis": list(axis),
        "youngs_modulus_axial": E_A,
        "youngs_modulus_transverse": E_T,
        "poisson_ratio_transverse": NU_T,
        "poisson_ratio_axial": NU_A,
        "shear_modulus_axial": G_A,
        "density": 1000.0,
        **more,
    }


def ti_box(nodes=(5, 4, 6), spacing=0.01, axis=(0.0, 0.0, 1.0), **settings) -> dict:
    spec = box_spec(nodes, spacing, fpm_settings={"stiffness": "families+volume", **settings})
    spec["material"] = ti(axis)
    return spec


def expected_strain(axis, load: int, p: float) -> np.ndarray:
    """(3, 3) the analytic strain under uniaxial stress p (Pa) along the solid's axis ``load``,
    from the material's definition: in the material's frame (axis third) eps = S sigma with
    eps_t = sigma_t / E_t - nu_t sigma_t' / E_t - nu_a sigma_a / E_a, eps_a = sigma_a / E_a -
    nu_a (sigma_t + sigma_t') / E_a, gamma = tau / G."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(helper, a)
    e1 /= np.linalg.norm(e1)
    r = np.column_stack([e1, np.cross(a, e1), a])  # local -> solid
    sigma = np.zeros((3, 3))
    sigma[load, load] = p
    s = r.T @ sigma @ r  # in the material's frame
    eps = np.zeros((3, 3))
    eps[0, 0] = s[0, 0] / E_T - NU_T * s[1, 1] / E_T - NU_A * s[2, 2] / E_A
    eps[1, 1] = s[1, 1] / E_T - NU_T * s[0, 0] / E_T - NU_A * s[2, 2] / E_A
    eps[2, 2] = s[2, 2] / E_A - NU_A * (s[0, 0] + s[1, 1]) / E_A
    g_t = E_T / (2 * (1 + NU_T))
    eps[0, 1] = eps[1, 0] = s[0, 1] / (2 * g_t)
    eps[1, 2] = eps[2, 1] = s[1, 2] / (2 * G_A)
    eps[0, 2] = eps[2, 0] = s[0, 2] / (2 * G_A)
    return r @ eps @ r.T


def uniaxial_supports(x: np.ndarray, load: int) -> np.ndarray:
    """(3N,) free unknowns: rollers on the face x_load = 0 (u_load = 0), the node at the origin
    held, and one component of a second node on that face against the rotation about the load
    axis: no other restraint, so a uniform stress state is free to form."""
    e, f = (load + 1) % 3, (load + 2) % 3
    held = np.zeros((len(x), 3), dtype=bool)
    face = np.abs(x[:, load]) < 1e-12
    held[face, load] = True
    origin = np.flatnonzero(np.all(np.abs(x) < 1e-12, axis=1))
    held[origin] = True
    far = np.flatnonzero(
        face & (np.abs(x[:, f]) < 1e-12) & (np.abs(x[:, e] - x[:, e].max()) < 1e-12)
    )
    held[far[0], f] = True
    return ~held.ravel()


def fitted_strain(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float]:
    """The uniform strain of ``u`` (N, 3) fitted as u = G x + c, and the largest misfit, m."""
    a = np.column_stack([x, np.ones(len(x))])
    coef, *_ = np.linalg.lstsq(a, u, rcond=None)
    g = coef[:3].T  # g[i, j] = du_i / dx_j
    misfit = float(np.abs(a @ coef - u).max())
    return (g + g.T) / 2, misfit


P = 100.0
"""Uniaxial stress, Pa."""


@pytest.mark.parametrize("integration", ["selective", "full"])
@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 1, 0.5)], ids=["axis z", "oblique axis"])
@pytest.mark.parametrize("load", [2, 0], ids=["along z", "along x"])
def test_hexahedra_reproduce_the_analytic_uniaxial_stretch(integration, axis, load):
    """Along the axis: eps_a = p / E_a and the sides narrow by nu_a eps_a; across: eps = p /
    E_t, the other in-plane side narrows by nu_t eps, the axial one by nu_a p / E_a. Uniform
    strain is in both elements' span (patch test), so the match is to round-off; with an
    oblique axis the same, shear strains included."""
    spec = ti_box(axis=axis)
    spec["reference"] = {"integration": integration}
    problem = fpm.load_problem(spec)
    x, hexahedra = problem.nodes, problem.solid.elements()
    k = hexahedron_stiffness(problem, x, hexahedra)
    # the face x_load = max carries p: each face (a rectangle) gives its corners a quarter each
    top = np.abs(x[:, load] - x[:, load].max()) < 1e-12
    f = np.zeros_like(x)
    faces = _hexahedron_faces(hexahedra, top)
    area = np.linalg.norm(
        np.cross(x[faces[:, 2]] - x[faces[:, 0]], x[faces[:, 1]] - x[faces[:, 0]]), axis=1
    )
    for c in range(4):
        np.add.at(f[:, load], faces[:, c], P * area / 4)
    u, _ = solve_dirichlet(k, f.ravel()[None], uniaxial_supports(x, load), x, "direct")
    eps, misfit = fitted_strain(x, u.reshape(-1, 3))
    exact = expected_strain(axis, load, P)
    assert misfit < 1e-9 * np.abs(exact).max() * 0.05
    np.testing.assert_allclose(eps, exact, atol=1e-9 * np.abs(exact).max())
    if axis == (0, 0, 1):  # the moduli as a user reads them
        if load == 2:
            assert eps[2, 2] == pytest.approx(P / E_A, rel=1e-9)
            assert -eps[0, 0] / eps[2, 2] == pytest.approx(NU_A, rel=1e-9)
        else:
            assert eps[0, 0] == pytest.approx(P / E_T, rel=1e-9)
            assert -eps[1, 1] / eps[0, 0] == pytest.approx(NU_T, rel=1e-9)
            assert -eps[2, 2] == pytest.approx(NU_A * P / E_A, rel=1e-9)


def _hexahedron_faces(hexahedra: np.ndarray, on: np.ndarray) -> np.ndarray:
    """(F, 4) the quadrilateral faces of ``hexahedra`` whose 4 corners are all ``on``."""
    quads = np.array(
        [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    )
    faces = hexahedra[:, quads].reshape(-1, 4)
    return faces[np.all(on[faces], axis=1)]


def box_tetrahedra(n: tuple[int, int, int], size: tuple[float, float, float]):
    """A box [0, size] of n cells a side, each split into 6 tetrahedra (Kuhn)."""
    kuhn = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
    g = [np.linspace(0.0, s, m + 1) for s, m in zip(size, n, strict=True)]
    nodes = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(nodes)).reshape(n[0] + 1, n[1] + 1, n[2] + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*[np.arange(m) for m in n], indexing="ij"))
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    tets = corners[:, kuhn].reshape(-1, 4)
    flip = TetMesh(nodes, tets).volumes < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return nodes, tets


@pytest.mark.parametrize("axis", [(0, 0, 1), (1, 1, 0.5)], ids=["axis z", "oblique axis"])
@pytest.mark.parametrize("load", [2, 0], ids=["along z", "along x"])
def test_tetrahedra_reproduce_the_analytic_uniaxial_stretch(axis, load):
    """The same stretches on 10-node tetrahedra (the reference on a tetrahedral mesh): a face
    of a 6-node triangle takes a uniform traction as a third of its area at each mid-edge
    node and none at its corners."""
    spec = ti_box(axis=axis)
    problem = fpm.load_problem(spec)
    nodes, tets = box_tetrahedra((3, 2, 4), (0.04, 0.03, 0.05))
    mesh = tet10.quadratic_mesh(nodes, tets)
    c, _ = tetrahedron_elasticity(problem, mesh.nodes, mesh.corners)
    k = tet10.stiffness_matrix(mesh, c)
    x = mesh.nodes
    faces, owner = TetMesh(mesh.nodes, mesh.corners).boundary
    on = np.abs(x[:, load] - x[:, load].max()) < 1e-12
    loaded = np.all(on[faces], axis=1)
    f = np.zeros_like(x)
    local_edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    for face, tet in zip(faces[loaded], owner[loaded], strict=True):
        area = np.linalg.norm(np.cross(x[face[1]] - x[face[0]], x[face[2]] - x[face[0]])) / 2
        element = mesh.elements[tet]
        for a, b in [(face[0], face[1]), (face[1], face[2]), (face[0], face[2])]:
            la, lb = list(element[:4]).index(a), list(element[:4]).index(b)
            edge = local_edges.index((min(la, lb), max(la, lb)))
            f[element[4 + edge], load] += P * area / 3
    u, _ = solve_dirichlet(k, f.ravel()[None], uniaxial_supports(x, load), x, "direct")
    eps, misfit = fitted_strain(x, u.reshape(-1, 3))
    exact = expected_strain(axis, load, P)
    assert misfit < 1e-9 * np.abs(exact).max() * 0.05
    np.testing.assert_allclose(eps, exact, atol=1e-9 * np.abs(exact).max())


def isotropic_as_ti(e: float, nu: float) -> dict:
    return {
        "type": "transversely-isotropic",
        "axis": [0.3, -0.2, 1.0],
        "youngs_modulus_axial": e,
        "youngs_modulus_transverse": e,
        "poisson_ratio_transverse": nu,
        "poisson_ratio_axial": nu,
        "shear_modulus_axial": e / (2 * (1 + nu)),
        "density": 1040.0,
    }


@pytest.mark.parametrize("reference", ["hex8", "tet10"])
def test_isotropic_constants_give_the_isotropic_reference(reference):
    """solve_fem with the five constants of an isotropic solid (any axis) is the isotropic
    reference (hexahedra: the general B-bar equals the split one; tetrahedra: the same C)."""
    spec = box_spec((4, 4, 4), 0.01, forces=[{"at": [0.03, 0.03, 0.03], "vector": [1e-3, 0, 2e-3]}])
    spec["fpm"] = {"stiffness": "families+volume"}
    if reference == "tet10":
        nodes, tets = box_tetrahedra((3, 3, 3), (0.03, 0.03, 0.03))
        spec["reference"] = {
            "mesh": {"nodes": nodes.tolist(), "tetrahedra": tets.tolist()},
            **AS_GIVEN,
        }
    else:
        spec["reference"] = dict(AS_GIVEN)
    iso = fpm.solve_fem(fpm.load_problem(spec)).displacements
    other = copy.deepcopy(spec)
    other["material"] = isotropic_as_ti(
        spec["material"]["youngs_modulus"], spec["material"]["poisson_ratio"]
    )
    aniso = fpm.solve_fem(fpm.load_problem(other)).displacements
    np.testing.assert_allclose(aniso, iso, atol=1e-9 * np.abs(iso).max())


# --- the lattice ---------------------------------------------------------------------------------


def test_closed_form_start_is_the_continuum_start_for_an_isotropic_solid():
    problem = fpm.load_problem(ti_box())
    names = family_names(problem)
    assert names == ("axis", "face", "body", "kappa", "axial_scale")
    iso = isotropic_as_ti(1e4, 0.45)
    k, kappa, s, misfit = closed_form_start(
        type("M", (), {**iso, "axis": (0, 0, 1)})(), 0.01, 3, 1e-3 * 1e4 / 2.9
    )
    mu, lam = 1e4 / 2.9, 1e4 * 0.45 / (1.45 * 0.1)
    assert s == pytest.approx(1.0, abs=1e-6) and misfit < 1e-9
    assert kappa == pytest.approx(lam - mu, rel=1e-6)
    assert k[1] == pytest.approx(mu * 0.01, rel=0.01) and k[2] < 1e-2 * mu * 0.01


def lattice_moduli(theta, h):
    """(E_a, E_t) of the lattice's continuum constants (axis along z)."""
    c11, c33, c12, c13, c44, c66 = lattice_constants(theta[:3], theta[3], theta[4], h)
    c = np.array([[c11, c12, c13], [c12, c11, c13], [c13, c13, c33]])
    s = np.linalg.inv(c)
    return 1 / s[2, 2], 1 / s[0, 0]


def test_closed_form_lattice_stretches_as_the_material_along_and_across_the_axis():
    """The lattice of the closed-form start, under the uniaxial stretches: its moduli along and
    across the axis against E_a and E_t (measured: 48.1 kPa against 50, 10.9 kPa against 10;
    central springs and an isotropic volume term cannot meet all six constants: here they
    would need kappa = C13 - C44 < 0 and kappa = C12 - C66 > 0 at once)."""
    problem = fpm.load_problem(ti_box())
    theta = continuum_start(problem)
    e_a, e_t = lattice_moduli(theta, problem.h)
    assert theta[-1] == pytest.approx(7.83, rel=0.01)  # the axial scale
    assert e_a == pytest.approx(E_A, rel=0.05)
    assert e_t == pytest.approx(E_T, rel=0.10)


def relative(problem, reference, theta) -> list[float]:
    """Per load case, the static equilibria's relative discrepancy at theta, %."""
    r = reference_displacements(reference, problem)
    cost = StaticCost(problem, r, None)
    return [
        100 * c / float(np.linalg.norm(r[j], axis=1).sum())
        for j, c in enumerate(cost(theta).case_costs)
    ]


def test_the_fit_finds_the_axial_scale_and_beats_an_isotropic_lattice():
    """Stage 1 on a small box (bottom clamped), the top face pulled along the axis and sheared,
    the side x+ pulled across it. The axial scale is fitted with the families and kappa and
    keeps the stiff axis (s about 8); the lattice fits the reference better than an isotropic
    lattice fitted to the same reference, most of all across the axis (measured: 16.5 / 2.7 /
    2.4% against 15.9 / 3.8 / 11.0%; an isotropic box fits its own reference to 7.7 / 1.4 /
    1.8%). kappa ends at its floor: this material's C13 - C44 < 0 asks for a negative volume
    stiffness."""
    face = [
        {"face": "z+", "vector": [0, 0, 0.05], "distribute": True},
        {"face": "z+", "vector": [0.02, 0, 0], "distribute": True},
        {"face": "x+", "vector": [0.05, 0, 0], "distribute": True},
    ]
    spec = ti_box(nodes=(5, 5, 6))
    spec["load_cases"] = [{"forces": [f]} for f in face]
    spec["annealing"] = {"chains": 1}
    spec["reference"] = dict(AS_GIVEN)
    problem = fpm.load_problem(spec)
    reference = fpm.solve_fem(problem)
    x, cost = stage_one(problem, reference)
    assert len(x) == 5 and 4.0 < x[-1] < 16.0
    iso = copy.deepcopy(spec)
    iso["material"] = {"youngs_modulus": E_T, "poisson_ratio": NU_T, "density": 1000.0}
    iso_problem = fpm.load_problem(iso)
    iso_x, iso_cost = stage_one(iso_problem, reference)  # the same reference, no axial scale
    assert cost < 0.85 * iso_cost
    fitted, isotropic = relative(problem, reference, x), relative(iso_problem, reference, iso_x)
    assert fitted[2] < 0.5 * isotropic[2] and max(fitted) < 20.0
    # the stored form reads back (the axial scale is in 'stiffness')
    record = {
        "stiffness": stiffness_dict(problem, x),
        "volume_stiffness": volume_stiffness(problem, x),
    }
    assert record["stiffness"]["axial_scale"] == x[-1]
    assert fitted_theta(problem, record) == pytest.approx(x)
    springs = model_stiffness(problem, x).springs / assembly_weights(problem)
    along = (
        np.abs(np.diff(problem.nodes[problem.solid.springs], axis=1)[:, 0, 2]) > 0.99 * problem.h
    )
    edges = problem.solid.families == 0
    np.testing.assert_allclose(springs[along & edges], x[0] * x[-1], rtol=1e-12)
    np.testing.assert_allclose(springs[~along & edges], x[0], rtol=1e-12)


# --- refusals ------------------------------------------------------------------------------------


def test_a_tensor_that_is_not_positive_definite_is_refused_naming_the_field():
    spec = ti_box()
    spec["material"]["poisson_ratio_axial"] = 1.2  # 1 - 0.45 - 2 1.44 / 5 < 0
    [(loc, msg)] = spec_errors(spec)
    assert loc == ("material", "poisson_ratio_axial") and "not positive definite" in msg


@pytest.mark.parametrize(
    ("change", "where", "words"),
    [
        ({"fpm": {"stiffness": "single"}}, ("fpm", "stiffness"), "families+volume"),
        (
            {"fpm": {"stiffness": "families+volume", "stiffness_scale": [1, 1, 2]}},
            ("fpm", "stiffness_scale"),
            "axial scale is fitted",
        ),
        ({"material": {"type": "orthotropic"}}, ("material", "type"), "unknown material type"),
        ({"material": {"axis": [0, 0, 0]}}, ("material", "axis"), "must not be zero"),
        ({"material": {"model": "neo-hookean"}}, ("material", "model"), "'linear'"),
    ],
)
def test_bad_transversely_isotropic_specs_are_refused_naming_the_field(change, where, words):
    spec = ti_box()
    for part, values in change.items():
        spec[part] = {**spec[part], **values}
    errors = spec_errors(spec)
    assert any(loc == where and words in msg for loc, msg in errors), errors
