"""The FEM reference (paper Sec. 4.1) against mathematics: exact fields, rigid-body modes,
analytic bar and beam solutions, convergence rate, and the errors a user can run into."""

from __future__ import annotations

import copy
import json
from functools import partial
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from pyamg.relaxation.relaxation import block_gauss_seidel
from pyamg.util.utils import get_block_diag
from pydantic import ValidationError

import fpm
from fpm.fem.assembly import identical_elements, keep_nodes, stiffness_matrix
from fpm.fem.elasticity import (
    constitutive_matrix,
    element_stiffness,
    physical_gradients,
    strain_displacement,
)
from fpm.fem.linear_solver import (
    NegativeCurvature,
    amg_hierarchy,
    conjugate_gradients,
    rigid_body_modes,
    v_cycle,
)
from fpm.fem.reference import FemError, FemResult, solve_dirichlet
from fpm.model.geometry import box_hexahedra
from fpm.model.hexahedron import GAUSS_POINTS, NATURAL, shape_function_gradients, shape_functions
from store import records

E, NU = 2.0e5, 0.3


def lattice(shape: tuple[int, int, int], size: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) nodes of a box lattice, x fastest (the order of fpm.model.geometry)."""
    axes = [np.linspace(0, s, n) for s, n in zip(size, shape, strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def distorted_mesh(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 3x3x3-element unit cube whose interior nodes are moved by up to 0.25 h.

    Returns nodes (64, 3), hexahedra (27, 8) and boundary (64,) bool.
    """
    shape = (4, 4, 4)
    nodes = lattice(shape, (1.0, 1.0, 1.0))
    boundary = np.any((nodes < 1e-12) | (nodes > 1 - 1e-12), axis=1)
    rng = np.random.default_rng(seed)
    nodes[~boundary] += rng.uniform(-0.25, 0.25, (int((~boundary).sum()), 3)) / 3
    return nodes, box_hexahedra(shape), boundary


def face_weights(shape: tuple[int, int, int], size: tuple[float, float, float], axis: int):
    """(N,) consistent nodal areas, m^2, of the lattice face normal to ``axis`` at its far end.

    A uniform traction p on bilinear faces gives node i the force p * weight_i.
    """
    w1 = []
    for a in range(3):
        n, h = shape[a], size[a] / (shape[a] - 1)
        w = np.full(n, h)
        w[[0, -1]] = h / 2
        if a == axis:
            w = np.zeros(n)
            w[-1] = 1.0
        w1.append(w)
    return (w1[2][:, None, None] * w1[1][None, :, None] * w1[0][None, None, :]).ravel()


# --- constitutive matrix and shape functions -------------------------------------------------


def test_constitutive_matrix_is_hookes_law():
    c = constitutive_matrix(E, NU)
    s = np.linalg.inv(c)  # compliance: 1/E on the diagonal, -nu/E off it, 1/G for shear
    assert np.allclose(s[:3, :3], (np.eye(3) * (1 + NU) - NU) / E)
    assert np.allclose(np.diag(s)[3:], 2 * (1 + NU) / E)
    assert np.allclose(c, c.T)
    assert c[0, 0] == pytest.approx(E * (1 - NU) / ((1 + NU) * (1 - 2 * NU)))


def test_shape_functions_interpolate_and_sum_to_one():
    assert np.allclose([shape_functions(p) for p in NATURAL], np.eye(8))
    rng = np.random.default_rng(1)
    for p in rng.uniform(-1, 1, (5, 3)):
        assert shape_functions(p).sum() == pytest.approx(1.0)
        assert np.allclose(shape_function_gradients(p).sum(axis=0), 0.0)
        step = 1e-6
        fd = [
            (shape_functions(p + step * e) - shape_functions(p - step * e)) / (2 * step)
            for e in np.eye(3)
        ]
        assert np.allclose(np.array(fd).T, shape_function_gradients(p), atol=1e-9)


# --- element and global stiffness -------------------------------------------------------------


def test_strain_energy_of_a_linear_field_is_exact_on_a_distorted_element():
    rng = np.random.default_rng(2)
    x = (NATURAL + rng.uniform(-0.3, 0.3, (8, 3)))[None]  # (1, 8, 3)
    grad = rng.normal(size=(3, 3)) * 1e-3  # u = grad @ x
    eps = np.array(
        [grad[0, 0], grad[1, 1], grad[2, 2], grad[0, 1] + grad[1, 0]]
        + [grad[1, 2] + grad[2, 1], grad[2, 0] + grad[0, 2]]
    )
    c = constitutive_matrix(E, NU)
    u = (x[0] @ grad.T).ravel()
    volume = sum(physical_gradients(x, p)[1][0] for p in GAUSS_POINTS)
    for p in GAUSS_POINTS:
        b = strain_displacement(physical_gradients(x, p)[0])[0]
        assert np.allclose(b @ u, eps)
    ke = element_stiffness(x, c)[0]
    assert u @ ke @ u == pytest.approx(volume * eps @ c @ eps, rel=1e-12)


def test_unconstrained_stiffness_is_symmetric_with_six_rigid_body_modes():
    nodes, hexahedra, _ = distorted_mesh()
    k = stiffness_matrix(nodes, hexahedra, constitutive_matrix(E, NU)).toarray()
    assert np.allclose(k, k.T, rtol=0, atol=1e-12 * np.abs(k).max())
    eig = np.linalg.eigvalsh(k)
    assert np.all(np.abs(eig[:6]) < 1e-10 * eig[-1])
    assert eig[6] > 1e-4 * eig[-1]
    assert np.allclose(k @ rigid_body_modes(nodes), 0, atol=1e-10 * eig[-1])


def test_identical_elements_found_once():
    nodes = lattice((5, 4, 3), (0.4, 0.3, 0.2))
    shapes, which = identical_elements(nodes[box_hexahedra((5, 4, 3))])
    assert len(shapes) == 1 and np.all(which == 0)
    nodes, hexahedra, _ = distorted_mesh()
    assert len(identical_elements(nodes[hexahedra])[0]) == len(hexahedra)


# --- patch tests ------------------------------------------------------------------------------


def test_patch_test_linear_field_reproduced_on_distorted_mesh():
    nodes, hexahedra, boundary = distorted_mesh(seed=3)
    k = stiffness_matrix(nodes, hexahedra, constitutive_matrix(E, NU)).tocsr()
    grad = np.array([[1.0, 0.2, -0.3], [0.1, -0.5, 0.4], [0.3, 0.2, 0.7]]) * 1e-3
    exact = (nodes @ grad.T + [1e-4, -2e-4, 3e-4]).ravel()
    inner = np.repeat(~boundary, 3)
    # Interior nodes are in equilibrium under the linear field with no force ...
    assert np.allclose((k @ exact)[inner], 0, atol=1e-9 * np.abs(k @ exact).max())
    # ... and solving for them with the boundary prescribed gives the field back.
    kii = k[inner][:, inner].tocsc()
    rhs = -(k[inner][:, ~inner] @ exact[~inner])
    assert np.allclose(spla.spsolve(kii, rhs), exact[inner], rtol=0, atol=1e-12)


def test_cube_under_uniform_traction_has_constant_stress():
    """Rollers on x=0, y=0, z=0; traction p on z=L: sigma = (0, 0, p, 0, 0, 0) everywhere."""
    shape, size, p = (4, 4, 4), (1.0, 1.0, 1.0), 1e3
    nodes = lattice(shape, size)
    hexahedra = box_hexahedra(shape)
    c = constitutive_matrix(E, NU)
    forces = np.zeros((len(nodes), 3))
    forces[:, 2] = p * face_weights(shape, size, 2)
    free = (nodes > 1e-12).ravel()  # a component is held where its coordinate is 0
    u, residuals = solve_dirichlet(
        stiffness_matrix(nodes, hexahedra, c), forces.ravel()[None], free, nodes, "direct"
    )
    assert residuals[0] < 1e-12
    x = nodes[hexahedra]
    ue = u[0].reshape(-1, 3)[hexahedra].reshape(-1, 24)
    for point in GAUSS_POINTS:
        stress = np.einsum(
            "pq,hqa,ha->hp", c, strain_displacement(physical_gradients(x, point)[0]), ue
        )
        assert np.allclose(stress, [0, 0, p, 0, 0, 0], rtol=0, atol=1e-9 * p)


# --- analytic solutions -----------------------------------------------------------------------


def test_bar_in_uniaxial_tension_stretches_and_contracts_by_poisson():
    shape, size = (11, 3, 3), (1.0, 0.1, 0.1)
    sigma, e, nu = 2e4, 7e6, 0.35
    nodes = lattice(shape, size)
    forces = np.zeros((len(nodes), 3))
    forces[:, 0] = sigma * face_weights(shape, size, 0)
    free = (nodes > 1e-12).ravel()  # symmetry-plane rollers on x=0, y=0, z=0
    k = stiffness_matrix(nodes, box_hexahedra(shape), constitutive_matrix(e, nu))
    u = solve_dirichlet(k, forces.ravel()[None], free, nodes, "direct")[0][0].reshape(-1, 3)
    strain = sigma / e
    assert np.allclose(u[:, 0], strain * nodes[:, 0], rtol=0, atol=1e-12)
    assert np.allclose(u[:, 1], -nu * strain * nodes[:, 1], rtol=0, atol=1e-12)
    assert np.allclose(u[:, 2], -nu * strain * nodes[:, 2], rtol=0, atol=1e-12)
    assert u[:, 0].max() == pytest.approx(sigma * size[0] / e, rel=1e-10)


def cantilever_spec(m: int, length: float, b: float, load: float, e: float) -> dict[str, Any]:
    """A square cantilever clamped at x=0 with m elements through its width b and 10 m along it,
    the end load spread over its free end as a uniform shear traction (consistent forces)."""
    shape = (10 * m + 1, m + 1, m + 1)
    size = (length, b, b)
    w = face_weights(shape, size, 0) * load / b**2
    return {
        "material": {"youngs_modulus": e, "poisson_ratio": 0.0, "density": 1000.0},
        "geometry": {"type": "box", "size": list(size), "nodes": list(shape)},
        "fixed": [{"face": "x-"}],
        "load_cases": [
            {"forces": [{"node": int(i), "vector": [0, 0, float(w[i])]} for i in np.flatnonzero(w)]}
        ],
    }


def test_cantilever_converges_to_beam_theory_at_second_order():
    """Tip deflection vs Timoshenko, P L^3 / (3 E I) + P L / (kappa G A), nu = 0 (no clamp
    Poisson effect); trilinear hexahedra converge as h^2."""
    length, b, load, e = 1.0, 0.1, 1.0, 1e7
    beam = load * length**3 / (3 * e * b**4 / 12) + load * length / (5 / 6 * e / 2 * b**2)
    widths, errors = [], []
    for m in (2, 3, 4, 6):
        spec = cantilever_spec(m, length, b, load, e)
        result = fpm.solve_fem(fpm.load_problem(spec))
        tip = result.displacements[0][np.isclose(result.nodes[:, 0], length), 2].mean()
        widths.append(b / m)
        errors.append(abs(tip - beam) / beam)
    slope = np.polyfit(np.log(widths), np.log(errors), 1)[0]
    assert errors[-1] < 0.05
    assert 1.7 < slope < 2.4, (errors, slope)


# --- the public API ---------------------------------------------------------------------------

SPEC: dict[str, Any] = {
    "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.45, "density": 1040.0},
    "geometry": {"type": "box", "size": [0.04, 0.03, 0.05], "nodes": [5, 4, 6]},
    "fixed": [{"face": "z-"}],
    "load_cases": [
        {"name": "pull", "forces": [{"at": [0.02, 0.01, 0.05], "vector": [0, 0, 0.1]}]},
        {
            "name": "shear",
            "forces": [
                {"at": [0.0, 0.0, 0.05], "vector": [0.05, 0, 0]},
                {"at": [0.04, 0.03, 0.03], "vector": [0, -0.02, 0.01]},
            ],
        },
    ],
}


def with_geometry(geometry: dict[str, Any], spec: dict[str, Any] = SPEC) -> dict[str, Any]:
    out = copy.deepcopy(spec)
    out["geometry"] = geometry
    return out


def by_position(result: FemResult) -> np.ndarray:
    """(L, N, 3) displacements with nodes sorted by (x, y, z)."""
    order = np.lexsort(result.nodes.T[::-1])
    return result.displacements[:, order]


def test_box_voxels_and_mesh_of_one_solid_agree():
    box = fpm.solve_fem(fpm.load_problem(SPEC))
    voxels = with_geometry(
        {"type": "voxels", "occupancy": np.ones((4, 3, 5), bool).tolist(), "spacing": [0.01] * 3}
    )
    nodes = lattice((5, 4, 6), (0.04, 0.03, 0.05))
    # The mesh lists its nodes in reverse, so agreement does not hang on node numbering.
    order = np.arange(len(nodes))[::-1]
    hexahedra = np.argsort(order)[box_hexahedra((5, 4, 6))]
    mesh = with_geometry(
        {"type": "mesh", "nodes": nodes[order].tolist(), "hexahedra": hexahedra.tolist()}
    )
    scale = np.abs(box.displacements).max()
    for spec in (voxels, mesh):
        other = fpm.solve_fem(fpm.load_problem(spec))
        assert np.allclose(by_position(other), by_position(box), rtol=0, atol=1e-10 * scale)


def test_displacements_are_linear_in_force_and_inverse_in_youngs_modulus():
    base = fpm.solve_fem(fpm.load_problem(SPEC)).displacements
    doubled = copy.deepcopy(SPEC)
    for case in doubled["load_cases"]:
        for force in case["forces"]:
            force["vector"] = [2 * v for v in force["vector"]]
    assert np.allclose(fpm.solve_fem(fpm.load_problem(doubled)).displacements, 2 * base)
    stiffer = copy.deepcopy(SPEC)
    stiffer["material"]["youngs_modulus"] *= 10
    assert np.allclose(fpm.solve_fem(fpm.load_problem(stiffer)).displacements, base / 10)


def test_direct_and_multigrid_solvers_agree():
    problem = fpm.load_problem(SPEC)
    direct = fpm.solve_fem(problem, method="direct")
    amg = fpm.solve_fem(problem, method="amg")
    assert direct.method == "direct" and amg.method == "amg"
    assert max(amg.residuals) < 1e-8 and max(direct.residuals) < 1e-12
    scale = np.abs(direct.displacements).max()
    assert np.allclose(amg.displacements, direct.displacements, rtol=0, atol=1e-7 * scale)


def test_load_cases_solved_on_threads_are_the_solves_alone(monkeypatch: pytest.MonkeyPatch):
    """The multigrid path's load cases run on threads: each column is, bit for bit, what
    CG gives for it alone (two cases or more take the threaded path)."""
    import fpm.fem.linear_solver as linear_solver

    problem = fpm.load_problem(SPEC)
    assert len(problem.all_cases) >= 2
    threaded = fpm.solve_fem(problem, method="amg").displacements
    monkeypatch.setattr(linear_solver, "COLUMN_THREADS", 1)
    alone = fpm.solve_fem(fpm.load_problem(SPEC), method="amg").displacements
    assert np.array_equal(threaded, alone)


def test_result_round_trips_through_json():
    result = fpm.solve_fem(fpm.load_problem(SPEC))
    assert result.displacements.shape == (2, 120, 3)
    assert result.load_cases == ["pull", "shear"]
    assert np.all(result.displacements[:, result.nodes[:, 2] == 0] == 0)
    back = FemResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert np.array_equal(back.displacements, result.displacements)
    assert np.array_equal(back.nodes, result.nodes)
    assert back.residuals == result.residuals and back.method == result.method
    assert np.array_equal(back.positions, result.nodes + result.displacements)


def test_result_round_trips_through_the_stores_raw_arrays():
    result = fpm.solve_fem(fpm.load_problem(SPEC))
    layout, raw = result.to_stored()
    assert len(raw) == 8 * (result.nodes.size + result.displacements.size)
    back = FemResult.from_stored(layout, raw)
    assert np.array_equal(back.displacements, result.displacements)
    assert np.array_equal(back.nodes, result.nodes)
    assert back.to_dict() == result.to_dict()
    # the store's own packing, without NumPy (a supplied reference, a restore): the same bytes
    assert records.pack_reference(result.to_dict()) == (layout, raw)
    assert records.unpack_reference(layout, raw) == result.to_dict()


# --- problems the FEM refuses -----------------------------------------------------------------


def test_network_has_no_fem():
    spec = with_geometry(
        {
            "type": "network",
            "nodes": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
            "springs": [[0, 1], [1, 2]],
            "masses": 1.0,
        }
    )
    spec["fixed"] = [{"node": 0}]
    spec["load_cases"] = [{"forces": [{"node": 2, "vector": [1, 0, 0]}]}]
    with pytest.raises(FemError, match="network.*no hexahedra"):
        fpm.solve_fem(fpm.load_problem(spec))


@pytest.mark.parametrize(
    ("fixed", "cause"),
    [
        ([], "no node is fixed"),
        ([{"node": 0}], "only one node is fixed"),
        ([{"box": [[0, 0, 0], [0.04, 0, 0]]}], "5 fixed nodes all lie on one line"),
        ([{"node": 0}, {"node": 6}], "2 fixed nodes all lie on one line"),
    ],
)
def test_unheld_solid_is_refused_with_its_cause(fixed: list, cause: str):
    spec = copy.deepcopy(SPEC)
    spec["fixed"] = fixed
    with pytest.raises(FemError, match=cause):
        fpm.solve_fem(fpm.load_problem(spec))


def test_block_hanging_on_an_edge_is_refused_until_held():
    """Two voxels sharing only an edge: the loose one can turn about that edge."""
    occupancy = np.zeros((2, 1, 2), bool)
    occupancy[0, 0, 0] = occupancy[1, 0, 1] = True
    spec = with_geometry({"type": "voxels", "occupancy": occupancy.tolist(), "spacing": [0.01] * 3})
    spec["fixed"] = [{"face": "z-"}]
    spec["load_cases"] = [{"forces": [{"at": [0.02, 0.01, 0.02], "vector": [0, 0, 1.0]}]}]
    with pytest.raises(FemError, match="part of the solid is not held"):
        fpm.solve_fem(fpm.load_problem(spec))
    spec["fixed"].append({"at": [0.02, 0.0, 0.02]})  # a third point off the hinge line
    result = fpm.solve_fem(fpm.load_problem(spec))
    assert max(result.residuals) < 1e-12


def test_inverted_hexahedron_is_refused():
    nodes = lattice((2, 2, 2), (1.0, 1.0, 1.0))
    hexahedron = box_hexahedra((2, 2, 2))[0][[4, 5, 6, 7, 0, 1, 2, 3]]  # upside down
    spec = with_geometry(
        {"type": "mesh", "nodes": nodes.tolist(), "hexahedra": [hexahedron.tolist()]}
    )
    spec["load_cases"] = [{"forces": [{"node": 7, "vector": [0, 0, 1.0]}]}]
    with pytest.raises(FemError, match="inverted"):
        fpm.solve_fem(fpm.load_problem(spec))


def test_a_node_outside_every_hexahedron_is_refused():
    nodes = lattice((2, 2, 2), (1.0, 1.0, 1.0)).tolist() + [[2.0, 2.0, 2.0]]
    spec = with_geometry({"type": "mesh", "nodes": nodes, "hexahedra": [[0, 1, 3, 2, 4, 5, 7, 6]]})
    spec["load_cases"] = [{"forces": [{"node": 8, "vector": [0, 0, 1.0]}]}]
    with pytest.raises(ValidationError, match="node 8 belongs to no hexahedron"):
        fpm.load_problem(spec)


# --- the shared linear solver (fpm.fem.linear_solver, also used by fpm.dynamics.equilibrium) ---


def spd(n: int) -> sp.csr_matrix:
    """(n, n) SPD: second differences plus 0.2 I (condition number ~ 20)."""
    return sp.diags([-np.ones(n - 1), 2.2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()


def no_preconditioner(r: np.ndarray) -> np.ndarray:
    return r.copy()


def test_cg_stops_at_the_tolerance_and_reports_its_iterations():
    a, b = spd(90), np.linspace(1.0, 2.0, 90)
    previous = 0
    for rtol in (1e-2, 1e-6, 1e-10):
        cg = conjugate_gradients(a, b, no_preconditioner, rtol=rtol, max_iterations=200)
        true = np.linalg.norm(b - a @ cg.x) / np.linalg.norm(b)
        assert cg.converged and cg.residual <= rtol
        assert np.isclose(true, cg.residual, rtol=1e-3, atol=1e-14)
        assert previous < cg.iterations < 90  # tighter takes longer
        previous = cg.iterations
    # One step short of the tolerance it had not stopped: the count is the first to meet it.
    short = conjugate_gradients(a, b, no_preconditioner, rtol=1e-10, max_iterations=previous - 1)
    assert not short.converged and short.iterations == previous - 1 and short.residual > 1e-10


def test_cg_takes_one_iteration_per_distinct_eigenvalue():
    a = sp.diags(np.repeat([1.0, 3.0, 10.0], 5)).tocsr()
    cg = conjugate_gradients(a, np.ones(15), no_preconditioner, rtol=1e-12, max_iterations=50)
    assert cg.iterations == 3 and np.allclose(cg.x, 1 / a.diagonal(), rtol=1e-12)


def test_cg_of_a_zero_right_hand_side_is_zero():
    cg = conjugate_gradients(spd(9), np.zeros(9), no_preconditioner, rtol=1e-9)
    assert cg.iterations == 0 and cg.converged and not np.any(cg.x)


def test_cg_detects_negative_curvature_on_an_indefinite_matrix():
    a = sp.diags(np.r_[np.ones(5), -np.ones(5)]).tocsr()
    with pytest.raises(NegativeCurvature) as caught:
        conjugate_gradients(a, np.r_[np.ones(5), 2 * np.ones(5)], no_preconditioner, rtol=1e-9)
    assert caught.value.args[0] == 1  # p = b: p.a p = 5 - 20 < 0 at once
    # An indefinite matrix can hide it for a while: b mostly on the positive part.
    a = sp.diags(np.r_[np.linspace(1.0, 2.0, 8), -1.0]).tocsr()
    with pytest.raises(NegativeCurvature) as caught:
        conjugate_gradients(a, np.r_[np.ones(8), 0.1], no_preconditioner, rtol=1e-12)
    assert caught.value.args[0] > 1


def test_cg_per_node_stop():
    """With nodal_stop, CG stops once every node's residual (3 unknowns) is at most it, even
    though the relative tolerance is far off."""
    a, b = spd(90), np.linspace(1.0, 2.0, 90)
    full = conjugate_gradients(a, b, no_preconditioner, rtol=1e-12, max_iterations=500)
    nodal = 1e-3 * np.abs(b).max()
    cg = conjugate_gradients(
        a, b, no_preconditioner, rtol=1e-12, max_iterations=500, nodal_stop=nodal
    )
    per_node = np.linalg.norm((b - a @ cg.x).reshape(-1, 3), axis=1)
    assert cg.converged and cg.iterations < full.iterations
    assert per_node.max() <= nodal * (1 + 1e-9) and cg.residual > 1e-12


def test_compiled_smoother_is_pyamgs_bit_for_bit_and_multigrid_cuts_iterations():
    """The AMG hierarchy (the FEM's from COMPILED_SMOOTHER_FROM unknowns, the equilibrium's)
    smooths its finest level with the compiled 3x3 block Gauss-Seidel; one sweep equals
    pyamg's exactly, and the V-cycle preconditions CG."""
    nodes = lattice((8, 8, 8), (0.1, 0.1, 0.1))
    k = stiffness_matrix(nodes, box_hexahedra((8, 8, 8)), constitutive_matrix(E, NU))
    free = nodes[:, 2] > 0
    kff = keep_nodes(k, free)
    modes = rigid_body_modes(nodes[free])
    hierarchy = amg_hierarchy(kff, modes)
    finest = hierarchy.levels[0]
    assert len(hierarchy.levels) > 1 and finest.A.blocksize == (3, 3)
    inverse = get_block_diag(finest.A, blocksize=3, inv_flag=True)
    rng = np.random.default_rng(0)
    b = rng.standard_normal(kff.shape[0])
    for sweep, smoother in (("forward", finest.presmoother), ("backward", finest.postsmoother)):
        ours = rng.standard_normal(len(b))
        theirs = ours.copy()
        smoother(finest.A, ours, b)
        block_gauss_seidel(finest.A, theirs, b, sweep=sweep, Dinv=inverse, blocksize=3)
        assert np.array_equal(ours, theirs)
    cycle = partial(v_cycle, hierarchy)
    with_amg = conjugate_gradients(kff, b, cycle, rtol=1e-9, max_iterations=1000)
    plain = conjugate_gradients(kff, b, no_preconditioner, rtol=1e-9, max_iterations=1000)
    assert with_amg.converged and plain.converged
    assert with_amg.iterations < plain.iterations / 3
    assert np.allclose(with_amg.x, plain.x, rtol=0, atol=1e-7 * np.abs(plain.x).max())


def test_multigrid_solve_refuses_a_matrix_that_is_not_positive_definite():
    """CG's negative-curvature detection reaches the FEM as its singular-stiffness error."""
    nodes = lattice((8, 8, 8), (0.1, 0.1, 0.1))
    k = stiffness_matrix(nodes, box_hexahedra((8, 8, 8)), constitutive_matrix(E, NU))
    indefinite = (k - 0.1 * k.diagonal().mean() * sp.eye(k.shape[0])).tobsr(blocksize=(3, 3))
    forces = np.zeros((1, k.shape[0]))
    forces[0, -1] = 1.0
    free = np.repeat(nodes[:, 2] > 0, 3)
    with pytest.raises(FemError, match="singular"):
        solve_dirichlet(indefinite, forces, free, nodes, "amg")
    u, residuals = solve_dirichlet(k, forces, free, nodes, "amg")  # the matrix itself is fine
    assert residuals.max() < 1e-8
