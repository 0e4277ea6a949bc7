"""The FEM reference as a solid: its own weight (consistent body forces) and no volumetric
locking (selective integration, B-bar), checked against a triquadratic hexahedron."""

from __future__ import annotations

import copy
import json
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from pydantic import ValidationError

import fpm
from fpm.fem.assembly import body_forces, stiffness_matrix
from fpm.fem.elasticity import (
    VOLUMETRIC,
    bulk_modulus,
    constitutive_matrix,
    element_stiffness,
    physical_gradients,
    strain_displacement,
)
from fpm.fem.hex27 import (
    LOCAL,
    quadratic_mesh,
    quadratic_shape_functions,
    solve_hex27,
    stiffness_matrix_27,
)
from fpm.fem.linear_solver import rigid_body_modes
from fpm.fem.reference import solve_dirichlet
from fpm.model.geometry import box_hexahedra, hexahedron_volumes
from fpm.model.hexahedron import GAUSS_POINTS, NATURAL
from store.hashing import fem_hash, fem_spec

ROOT = Path(__file__).resolve().parents[2]
PAPER_A: dict[str, Any] = json.loads((ROOT / "examples" / "paper-material-a.json").read_text())
E, NU, RHO = 2.0e5, 0.3, 1040.0
G = np.array([0.0, 0.0, -9.81])


def lattice(shape: tuple[int, int, int], size: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) nodes of a box lattice, x fastest (the order of fpm.model.geometry)."""
    axes = [np.linspace(0, s, n) for s, n in zip(size, shape, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def distorted_mesh(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 3x3x3-element unit cube, interior nodes moved by up to 0.25 h: nodes, hexahedra,
    boundary (bool)."""
    shape = (4, 4, 4)
    nodes = lattice(shape, (1.0, 1.0, 1.0))
    boundary = np.any((nodes < 1e-12) | (nodes > 1 - 1e-12), axis=1)
    rng = np.random.default_rng(seed)
    nodes[~boundary] += rng.uniform(-0.25, 0.25, (int((~boundary).sum()), 3)) / 3
    return nodes, box_hexahedra(shape), boundary


def mesh_spec(nodes: np.ndarray, hexahedra: np.ndarray, **fpm_settings: Any) -> dict[str, Any]:
    """A mesh spec: bottom (z = 0) fixed, a lateral and a vertical force at a top corner."""
    return {
        "material": {"youngs_modulus": E, "poisson_ratio": NU, "density": RHO},
        "geometry": {
            "type": "mesh",
            "nodes": nodes.tolist(),
            "hexahedra": hexahedra.tolist(),
        },
        "fixed": [{"face": "z-"}],
        "load_cases": [
            {"forces": [{"at": [1.0, 1.0, 1.0], "vector": [20.0, 0.0, 0.0]}]},
            {"forces": [{"at": [1.0, 1.0, 1.0], "vector": [0.0, 0.0, -50.0]}]},
        ],
        "fpm": fpm_settings,
    }


# --- integration: full is the previous element, selective is B-bar ----------------------------


def test_full_integration_is_the_previous_element_bit_for_bit():
    """``"full"`` is the element every earlier reference was computed with: the same sums in
    the same order (so Table 1, which names it, is unchanged)."""
    rng = np.random.default_rng(4)
    coords = (NATURAL + rng.uniform(-0.3, 0.3, (3, 8, 3))) * 0.01
    c = constitutive_matrix(E, 0.45)
    previous = np.zeros((3, 24, 24))
    for point in GAUSS_POINTS:
        grad, det = physical_gradients(coords, point)
        b = strain_displacement(grad)
        previous += np.einsum("hpa,pq,hqb->hab", b, c, b, optimize=True) * det[:, None, None]
    assert np.array_equal(element_stiffness(coords, c, "full"), previous)
    assert np.array_equal(element_stiffness(coords, c), previous)  # the element's default


def test_the_paper_examples_name_full_integration_and_keep_their_displacements():
    spec = fpm.load_problem(copy.deepcopy(PAPER_A)).spec
    assert spec.reference.integration == "full"
    u = fpm.solve_fem(fpm.load_problem(copy.deepcopy(PAPER_A))).displacements
    # the peak displacement at 0.25 N per node before selective integration existed
    assert u.max() == pytest.approx(0.015628993142556138, rel=1e-12)


def test_selective_integration_is_bbar_with_the_mean_dilatation():
    rng = np.random.default_rng(5)
    coords = NATURAL[None] + rng.uniform(-0.3, 0.3, (2, 8, 3))
    c = constitutive_matrix(E, 0.49)
    grads = [physical_gradients(coords, p) for p in GAUSS_POINTS]
    volume = sum(det for _, det in grads)
    mean_div = sum(g.reshape(2, 24) * det[:, None] for g, det in grads) / volume[:, None]
    expected = np.zeros((2, 24, 24))
    for grad, det in grads:
        b = strain_displacement(grad)
        bbar = b + VOLUMETRIC[None, :, None] * (mean_div - grad.reshape(2, 24))[:, None, :] / 3
        expected += np.einsum("hpa,pq,hqb->hab", bbar, c, bbar) * det[:, None, None]
    assert np.allclose(element_stiffness(coords, c, "selective"), expected, rtol=1e-12, atol=0)


def test_selective_on_a_parallelepiped_is_one_point_volumetric_integration():
    coords = np.array([[0.0, 0, 0], [2, 0.3, 0], [2.4, 1.5, 0.2], [0.4, 1.2, 0.2]])
    coords = np.concatenate([coords, coords + [0.1, 0.2, 0.9]])[None]
    c = constitutive_matrix(E, 0.45)
    kappa = bulk_modulus(c)
    assert kappa == pytest.approx(E / (3 * (1 - 2 * 0.45)))
    deviatoric = c - kappa * np.outer(VOLUMETRIC, VOLUMETRIC)
    expected = element_stiffness(coords, deviatoric, "full")
    grad, det = physical_gradients(coords, np.zeros(3))
    b = strain_displacement(grad)[0]
    expected += 8 * det[0] * kappa * np.outer(VOLUMETRIC @ b, VOLUMETRIC @ b)
    assert np.allclose(element_stiffness(coords, c, "selective"), expected, rtol=1e-12)


def test_selective_stiffness_has_six_rigid_modes_and_passes_the_patch_test():
    nodes, hexahedra, boundary = distorted_mesh(seed=3)
    k = stiffness_matrix(nodes, hexahedra, constitutive_matrix(E, 0.49), "selective")
    dense = k.toarray()
    eig = np.linalg.eigvalsh(dense)
    assert np.all(np.abs(eig[:6]) < 1e-10 * eig[-1]) and eig[6] > 1e-6 * eig[-1]
    assert np.allclose(dense @ rigid_body_modes(nodes), 0, atol=1e-10 * eig[-1])
    k = k.tocsr()
    grad = np.array([[1.0, 0.2, -0.3], [0.1, -0.5, 0.4], [0.3, 0.2, 0.7]]) * 1e-3
    exact = (nodes @ grad.T + [1e-4, -2e-4, 3e-4]).ravel()
    inner = np.repeat(~boundary, 3)
    rhs = -(k[inner][:, ~inner] @ exact[~inner])
    assert np.allclose(spla.spsolve(k[inner][:, inner].tocsc(), rhs), exact[inner], atol=1e-12)


def test_integration_is_a_validated_spec_field_and_part_of_the_references_identity():
    spec = copy.deepcopy(PAPER_A)
    del spec["reference"]
    default = fpm.load_problem(spec).spec
    assert default.reference.integration == "selective"
    spec["reference"] = {"integration": "reduced"}
    with pytest.raises(ValidationError) as caught:
        fpm.ProblemSpec.model_validate(spec)
    assert caught.value.errors()[0]["loc"] == ("reference", "integration")
    dumps = {}
    for integration in ("selective", "full"):
        spec["reference"] = {"integration": integration}
        dumps[integration] = fpm.ProblemSpec.model_validate(spec).model_dump(mode="json")
    assert fem_hash(dumps["selective"]) != fem_hash(dumps["full"])
    assert fem_spec(dumps["full"])["reference"] == {"integration": "full"}
    loaded = fpm.load_problem(fem_spec(dumps["full"]))  # the FEM job's spec loads as it is
    assert loaded.spec.reference.integration == "full"


# --- the triquadratic verification element ----------------------------------------------------


def test_quadratic_shape_functions_interpolate_and_sum_to_one():
    values = np.array([quadratic_shape_functions(p)[0] for p in LOCAL])
    assert np.allclose(values, np.eye(27), atol=1e-15)
    rng = np.random.default_rng(6)
    for p in rng.uniform(-1, 1, (4, 3)):
        n, grad = quadratic_shape_functions(p)
        assert n.sum() == pytest.approx(1.0) and np.allclose(grad.sum(axis=0), 0, atol=1e-12)
        fd = [
            (quadratic_shape_functions(p + h)[0] - quadratic_shape_functions(p - h)[0]) / 2e-6
            for h in 1e-6 * np.eye(3)
        ]
        assert np.allclose(np.array(fd).T, grad, atol=1e-8)


def test_quadratic_mesh_shares_edges_and_faces_and_keeps_fixed_faces_fixed():
    shape = (3, 3, 3)
    nodes = lattice(shape, (1.0, 1.0, 1.0))
    fixed = nodes[:, 2] < 1e-12
    mesh = quadratic_mesh(nodes, box_hexahedra(shape), fixed)
    assert len(mesh.nodes) == 5**3  # a 5x5x5 grid of the 2x2x2 elements
    assert np.allclose(mesh.nodes[: len(nodes)], nodes)
    assert len(np.unique(np.round(mesh.nodes, 12), axis=0)) == len(mesh.nodes)
    assert np.array_equal(mesh.fixed, mesh.nodes[:, 2] < 1e-12)


def test_hex27_passes_the_patch_test_on_a_distorted_mesh():
    """Uniform strain is reproduced exactly (the elements' geometry is trilinear, so a linear
    field lies in the triquadratic space)."""
    nodes, hexahedra, _ = distorted_mesh(seed=7)
    mesh = quadratic_mesh(nodes, hexahedra, np.zeros(len(nodes), dtype=bool))
    k = stiffness_matrix_27(mesh, nodes[hexahedra], constitutive_matrix(E, 0.49)).tocsr()
    boundary = np.any((mesh.nodes < 1e-12) | (mesh.nodes > 1 - 1e-12), axis=1)
    eig = np.linalg.eigvalsh(k.toarray())
    assert np.all(np.abs(eig[:6]) < 1e-10 * eig[-1]) and eig[6] > 1e-8 * eig[-1]
    grad = np.array([[1.0, 0.2, -0.3], [0.1, -0.5, 0.4], [0.3, 0.2, 0.7]]) * 1e-3
    exact = (mesh.nodes @ grad.T + [1e-4, -2e-4, 3e-4]).ravel()
    inner = np.repeat(~boundary, 3)
    rhs = -(k[inner][:, ~inner] @ exact[~inner])
    assert np.allclose(spla.spsolve(k[inner][:, inner].tocsc(), rhs), exact[inner], atol=1e-12)


def relative_gap(u: np.ndarray, reference: np.ndarray) -> float:
    """sum_i |u_i - r_i| / sum_i |r_i| over the nodes (Euclidean norms)."""
    return float(
        np.linalg.norm(u - reference, axis=-1).sum() / np.linalg.norm(reference, axis=-1).sum()
    )


def test_selective_hex8_does_not_lock_at_nu_049_against_hex27():
    """The paper's cube at nu = 0.49 (0.25 N per pulled node): selective integration within 7%
    of the triquadratic hexahedron on the same grid, full integration about 19% off."""
    spec = copy.deepcopy(PAPER_A)
    spec["material"]["poisson_ratio"] = 0.49
    spec["load_cases"] = spec["load_cases"][:1]
    gaps = {}
    for integration in ("selective", "full"):
        spec["reference"] = {"integration": integration}
        problem = fpm.load_problem(spec)
        gaps[integration] = fpm.solve_fem(problem).displacements
    forces = problem.load_cases[0].dense(len(problem.nodes))[None]
    hexahedra = problem.solid.elements()
    assert hexahedra is not None
    c = constitutive_matrix(1e4, 0.49)
    u27 = solve_hex27(problem.nodes, hexahedra, problem.fixed, c, forces)
    selective, full = (relative_gap(gaps[i], u27) for i in ("selective", "full"))
    assert selective < 0.07
    assert full > 0.10 and full > 2 * selective


# --- gravity: the solid's own weight ----------------------------------------------------------


def hand_body_forces(nodes: np.ndarray, hexahedra: np.ndarray, rho: float, g: np.ndarray):
    """int N_a rho g dV by 3x3x3 Gauss points, written out element by element."""
    pts = (-np.sqrt(0.6), 0.0, np.sqrt(0.6))
    wts = (5 / 9, 8 / 9, 5 / 9)
    out = np.zeros((len(nodes), 3))
    for hexa in hexahedra:
        x = nodes[hexa]
        for (r, wr), (s, ws), (t, wt) in product(zip(pts, wts, strict=True), repeat=3):
            n = np.array([(1 + r * a) * (1 + s * b) * (1 + t * c) / 8 for a, b, c in NATURAL])
            dn = (
                np.array(
                    [
                        [a * (1 + s * b) * (1 + t * c), b * (1 + r * a) * (1 + t * c)]
                        + [c * (1 + r * a) * (1 + s * b)]
                        for a, b, c in NATURAL
                    ]
                )
                / 8
            )
            det = np.linalg.det(dn.T @ x)
            for a in range(8):
                out[hexa[a]] += n[a] * rho * g * det * wr * ws * wt
    return out


def test_body_forces_of_a_box_are_the_lumped_weights():
    shape, size = (4, 3, 5), (0.3, 0.2, 0.4)
    nodes = lattice(shape, size)
    hexahedra = box_hexahedra(shape)
    f = body_forces(nodes, hexahedra, RHO, G)
    cell = np.prod(size) / np.prod(np.array(shape) - 1)
    corners = np.bincount(hexahedra.ravel(), minlength=len(nodes))
    assert np.allclose(f, RHO * cell / 8 * corners[:, None] * G, rtol=1e-13, atol=0)
    assert f.sum(axis=0) == pytest.approx(RHO * np.prod(size) * G, rel=1e-12)


def test_body_forces_of_a_distorted_mesh_match_a_hand_written_quadrature():
    nodes, hexahedra, _ = distorted_mesh(seed=8)
    nodes = nodes * [0.2, 0.1, 0.3]
    g = np.array([1.0, -2.0, -9.81])
    f = body_forces(nodes, hexahedra, RHO, g)
    assert np.allclose(f, hand_body_forces(nodes, hexahedra, RHO, g), rtol=1e-12, atol=0)
    volume = hexahedron_volumes(nodes, hexahedra).sum()
    assert volume == pytest.approx(0.2 * 0.1 * 0.3, rel=1e-12)
    assert np.allclose(f.sum(axis=0), RHO * volume * g, rtol=1e-12)


def test_lattice_mass_is_the_solids_mass():
    nodes, hexahedra, _ = distorted_mesh(seed=9)
    problem = fpm.load_problem(mesh_spec(nodes, hexahedra))
    volume = hexahedron_volumes(nodes, hexahedra).sum()
    assert problem.solid.masses.sum() == pytest.approx(RHO * volume, rel=1e-12)
    voxels = {
        "material": {"youngs_modulus": E, "poisson_ratio": NU, "density": RHO},
        "geometry": {
            "type": "voxels",
            "occupancy": [[[True, True], [True, False]], [[True, False], [False, False]]],
            "spacing": [0.01, 0.02, 0.03],
        },
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"at": [0.0, 0.0, 0.06], "vector": [0, 0, 1.0]}]}],
    }
    masses = fpm.load_problem(voxels).solid.masses
    assert masses.sum() == pytest.approx(RHO * 4 * 0.01 * 0.02 * 0.03, rel=1e-12)


@pytest.mark.parametrize("integration", ["selective", "full"])
def test_gravity_response_is_the_body_force_solution_and_superposes(integration: str):
    nodes, hexahedra, _ = distorted_mesh(seed=10)
    nodes = nodes * 0.05
    spec = mesh_spec(nodes, hexahedra)
    spec["load_cases"][0]["forces"][0]["at"] = [0.05, 0.05, 0.05]
    spec["load_cases"][1]["forces"][0]["at"] = [0.05, 0.05, 0.05]
    spec["reference"] = {"integration": integration}
    plain = fpm.load_problem(spec)
    weighed = fpm.load_problem({**spec, "fpm": {"gravity": G.tolist()}})
    u_f = fpm.solve_fem(plain).displacements
    u_fg = fpm.solve_fem(weighed).displacements
    # independently: K from the assembly, the hand-written consistent load, one solve
    c = constitutive_matrix(E, NU)
    k = stiffness_matrix(nodes, hexahedra, c, integration)
    body = hand_body_forces(nodes, hexahedra, RHO, G)
    free = np.repeat(~plain.fixed, 3)
    u_g, _ = solve_dirichlet(k, body.reshape(1, -1), free, nodes, "direct")
    u_g = u_g.reshape(-1, 3)
    for j in range(2):
        gravity_part = u_fg[j] - u_f[j]
        assert np.abs(gravity_part - u_g).max() <= 1e-4 * np.abs(u_g).max()  # 0.01%
        assert np.allclose(u_fg[j], u_f[j] + u_g, rtol=0, atol=1e-12 * np.abs(u_fg).max())
    assert np.linalg.norm(u_g, axis=1).max() > 0
    # reactions at the fixed nodes balance the weight (and the applied force)
    total_weight = RHO * hexahedron_volumes(nodes, hexahedra).sum() * G
    internal = (k @ u_fg[1].ravel()).reshape(-1, 3)
    applied = plain.load_cases[1].dense(len(nodes)) + body
    reactions = (internal - applied)[plain.fixed].sum(axis=0)
    expected = -(total_weight + applied.sum(axis=0) - body.sum(axis=0))
    assert np.allclose(reactions, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_gravity_in_the_neo_hookean_reference_is_a_dead_load():
    """Under its own weight (and a negligible force: a load case needs one) the neo-Hookean
    reference settles, at small strain, where the linear one does (full integration: the same
    2x2x2 points); without gravity it hardly moves."""
    shape = (4, 4, 4)
    spec: dict[str, Any] = {
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.3, "density": RHO},
        "geometry": {"type": "box", "size": [0.03, 0.03, 0.03], "nodes": list(shape)},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"node": 63, "vector": [1e-9, 0.0, 0.0]}]}],
        "fpm": {"gravity": [0.0, 0.0, -9.81]},
        "reference": {"integration": "full"},
    }
    linear = fpm.solve_fem(fpm.load_problem(spec)).displacements[0]
    nh_spec = copy.deepcopy(spec)
    nh_spec["material"]["model"] = "neo-hookean"
    nh = fpm.solve_fem(fpm.load_problem(nh_spec))
    u = nh.displacements[0]
    assert np.abs(u).max() > 0 and nh.residuals[0] < 1e-9
    # geometric nonlinearity at this strain (~1e-3) is of that order relative to u
    assert np.abs(u - linear).max() <= 2e-2 * np.abs(linear).max()
    without = copy.deepcopy(nh_spec)
    del without["fpm"]
    assert (
        np.abs(fpm.solve_fem(fpm.load_problem(without)).displacements).max()
        < 1e-6 * np.abs(u).max()
    )
