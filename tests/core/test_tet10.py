"""The 10-node tetrahedral reference (fpm/fem/tet10.py) against mathematics, against the
triquadratic hexahedron, and against an independent 10-node solver (scikit-fem)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from pydantic import ValidationError

import fpm
from fpm.fem import tet10
from fpm.fem.elasticity import constitutive_matrix
from fpm.fem.hex27 import (
    GAUSS_27,
    GAUSS_27_WEIGHTS,
    quadratic_shape_functions,
    stiffness_matrix_27,
)
from fpm.fem.hex27 import quadratic_mesh as hex27_mesh
from fpm.fem.linear_solver import factorize, rigid_body_modes
from fpm.fem.reference import solve_dirichlet
from fpm.model.hexahedron import jacobians
from fpm.model.tetrahedra import TetMesh, check_tetrahedra
from store.hashing import fem_hash

KUHN = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
"""Six tetrahedra around the diagonal 0-6 of a hexahedron (fpm.model.hexahedron order)."""


def cube_tetrahedra(
    n: int, size: float = 1.0, jitter: float = 0.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A cube [0, size]^3 split into n^3 hexahedra of 6 tetrahedra each; interior nodes moved
    at random by up to ``jitter`` of the spacing (a distorted mesh)."""
    g = np.linspace(0.0, size, n + 1)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    if jitter:
        inner = np.all((nodes > 1e-12) & (nodes < size - 1e-12), axis=1)
        shift = np.random.default_rng(seed).uniform(-1, 1, nodes.shape) * jitter * size / n
        nodes[inner] += shift[inner]
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*[np.arange(n)] * 3, indexing="ij"))
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    tets = corners[:, KUHN].reshape(-1, 4)
    inside_out = TetMesh(nodes, tets).volumes < 0
    tets[inside_out] = tets[inside_out][:, [0, 2, 1, 3]]
    return nodes, tets


def on_boundary(x: np.ndarray, size: float = 1.0) -> np.ndarray:
    return np.any((x < 1e-12) | (x > size - 1e-12), axis=1)


def relative_gap(u: np.ndarray, reference: np.ndarray) -> float:
    """sum_i |u_i - r_i| / sum_i |r_i| over the nodes (Euclidean norms)."""
    return float(
        np.linalg.norm(u - reference, axis=-1).sum() / np.linalg.norm(reference, axis=-1).sum()
    )


C = constitutive_matrix(5e3, 0.45)


def solve_imposed(mesh: tet10.Tet10Mesh, held: np.ndarray, imposed: np.ndarray, f: np.ndarray):
    """Displacements with ``imposed`` (M, 3) on the ``held`` (M,) nodes and forces ``f``."""
    k = tet10.stiffness_matrix(mesh, C).tocsr()
    free = np.repeat(~held, 3)
    u = np.where(held[:, None], imposed, 0.0).ravel()
    rhs = f.ravel()[free] - (k @ u)[free]
    u[free] = factorize(k[free][:, free], "direct", np.zeros((int(free.sum()), 6)))(rhs[:, None])[
        :, 0
    ]
    return u.reshape(-1, 3)


# --- the element --------------------------------------------------------------------------------


def test_patch_test_linear_field_reproduced_inside_on_a_distorted_mesh():
    """A linear displacement imposed on the boundary is reproduced at every inside node, corner
    and mid-edge alike, to round-off (no body force)."""
    nodes, tets = cube_tetrahedra(3, jitter=0.25)
    mesh = tet10.quadratic_mesh(nodes, tets)
    a = np.array([[1.0, 2.0, -1.0], [0.5, -1.0, 2.0], [3.0, 1.0, 1.0]]) * 1e-3
    exact = mesh.nodes @ a.T + [1e-3, -2e-3, 5e-4]
    held = on_boundary(mesh.nodes)
    u = solve_imposed(mesh, held, exact, np.zeros_like(exact))
    assert (~held[mesh.n_corners :]).sum() > 0  # there are inside mid-edge nodes
    assert np.abs(u - exact).max() < 1e-12 * np.abs(exact).max() * 1e3


def test_quadratic_field_with_its_body_force_reproduced_exactly():
    """A standing bar compressed by its own weight has a quadratic exact solution; with it on
    the boundary and the consistent weight, the inside reproduces it to round-off."""
    nodes, tets = cube_tetrahedra(2, jitter=0.2)
    mesh = tet10.quadratic_mesh(nodes, tets)
    e, nu, rho, g, height = 5e3, 0.45, 1000.0, 9.81, 1.0  # C is this E and nu
    x, y, z = mesh.nodes.T
    exact = np.stack(
        [
            nu * rho * g * (height - z) * x / e,
            nu * rho * g * (height - z) * y / e,
            -rho * g / e * (height * z - z**2 / 2) + nu * rho * g * (x**2 + y**2) / (2 * e),
        ],
        axis=1,
    )
    weight = tet10.body_forces(mesh, rho, np.array([0.0, 0.0, -g]))
    u = solve_imposed(mesh, on_boundary(mesh.nodes), exact, weight)
    assert np.abs(u - exact).max() < 1e-9 * np.abs(exact).max()


def test_rigid_body_modes_give_zero_force():
    nodes, tets = cube_tetrahedra(2, jitter=0.3)
    mesh = tet10.quadratic_mesh(nodes, tets)
    k = tet10.stiffness_matrix(mesh, C)
    modes = rigid_body_modes(mesh.nodes)
    assert np.abs(k @ modes).max() < 1e-12 * np.abs(k.data).max()


def test_assembly_in_chunks_is_the_sum_of_the_element_matrices(monkeypatch):
    """The global K, assembled in chunks of 7 elements (a compiled scatter of 3x3 blocks), is
    the dense sum of every element's 30 x 30 matrix at its nodes' unknowns."""
    nodes, tets = cube_tetrahedra(2, jitter=0.3)
    mesh = tet10.quadratic_mesh(nodes, tets)
    monkeypatch.setattr(tet10, "CHUNK", 7)
    k = tet10.stiffness_matrix(mesh, C).toarray()
    dense = np.zeros_like(k)
    ke = tet10.element_stiffness(mesh.nodes[mesh.corners], C)
    for element, matrix in zip(mesh.elements, ke, strict=True):
        dofs = (3 * element[:, None] + np.arange(3)).ravel()
        dense[np.ix_(dofs, dofs)] += matrix
    assert len(mesh.elements) > 3 * 7
    assert np.abs(k - dense).max() <= 1e-13 * np.abs(dense).max()


def test_load_cases_on_two_threads_are_each_solved_as_alone(monkeypatch):
    """The p-multigrid CG solves the load cases on up to COLUMN_THREADS threads: the same
    displacements, residuals and iterations, bit for bit, as one after another, and they
    solve K u = f."""
    from fpm.fem import linear_solver

    nodes, tets = cube_tetrahedra(3, jitter=0.25)
    mesh = tet10.quadratic_mesh(nodes, tets)
    k = tet10.stiffness_matrix(mesh, C)
    held = mesh.nodes[:, 2] < 1e-9
    free = np.repeat(~held, 3)
    forces = np.random.default_rng(7).normal(size=(3, 3 * len(mesh.nodes))) * free
    solved = {}
    for threads in (1, 2):
        monkeypatch.setattr(linear_solver, "COLUMN_THREADS", threads)
        solved[threads] = tet10.solve_p_multigrid(k, forces, free, mesh)
    (u1, r1, i1), (u2, r2, i2) = solved[1], solved[2]
    assert np.array_equal(u1, u2) and np.array_equal(r1, r2) and i1 == i2
    kff = k.tocsr()[free][:, free]
    for case in range(3):
        residual = kff @ u2[case, free] - forces[case, free]
        assert np.linalg.norm(residual) <= 1.01 * tet10.CG_TOLERANCE * np.linalg.norm(
            forces[case, free]
        )


def test_stiffness_is_symmetric_and_body_force_sums_to_the_weight():
    nodes, tets = cube_tetrahedra(2, size=0.1, jitter=0.3)
    mesh = tet10.quadratic_mesh(nodes, tets)
    k = tet10.stiffness_matrix(mesh, C).tocsr()
    assert abs(k - k.T).max() < 1e-12 * abs(k).max()
    weight = tet10.body_forces(mesh, 1040.0, np.array([0.0, -1.0, -9.81]))
    assert np.allclose(weight.sum(axis=0), 1040.0 * 1e-3 * np.array([0.0, -1.0, -9.81]))


def test_bar_under_axial_load_and_own_weight_against_the_analytic_solution():
    """A bar 1 x 1 x 4 on rollers (u_z = 0 at z = 0, symmetry planes x = 0, y = 0) under a
    uniform pull p on its top and its weight: sigma_zz = p - rho g (L - z), u_x = -nu sigma_zz
    x / E, u_z = (p z + rho g (z^2/2 - L z)) / E + nu rho g (x^2 + y^2) / (2 E). Quadratic, so
    reproduced to round-off at every refinement (1 and 2 cells across); the reactions balance
    the pull and the weight."""
    e, nu, rho, g, p = 5e3, 0.45, 1000.0, 9.81, 200.0
    for n in (1, 2):
        nodes, tets = cube_tetrahedra(n)
        nodes[:, 2] *= 4.0
        length = 4.0
        mesh = tet10.quadratic_mesh(nodes, tets)
        faces, _ = TetMesh(mesh.nodes, mesh.corners).boundary
        top = faces[np.all(nodes[faces][:, :, 2] > length - 1e-9, axis=1)]
        # consistent uniform traction on 6-node triangles: corners 0, mid-edges A/3
        load = np.zeros((len(mesh.nodes), 3))
        area = 0.5 * np.linalg.norm(
            np.cross(nodes[top[:, 1]] - nodes[top[:, 0]], nodes[top[:, 2]] - nodes[top[:, 0]]),
            axis=1,
        )
        tree = {tuple(x): i for i, x in enumerate(np.round(mesh.nodes, 12))}
        for tri, a in zip(top, area, strict=True):
            for i, j in ((0, 1), (1, 2), (2, 0)):
                mid = tree[tuple(np.round((nodes[tri[i]] + nodes[tri[j]]) / 2, 12))]
                load[mid, 2] += p * a / 3
        load += tet10.body_forces(mesh, rho, np.array([0.0, 0.0, -g]))
        x, y, z = mesh.nodes.T
        k = tet10.stiffness_matrix(mesh, constitutive_matrix(e, nu)).tocsr()
        stress = p - rho * g * (length - z)  # sigma_zz
        exact = np.stack(
            [
                -nu * stress * x / e,
                -nu * stress * y / e,
                (p * z + rho * g * (z**2 / 2 - length * z)) / e
                + nu * rho * g * (x**2 + y**2) / (2 * e),
            ],
            axis=1,
        )
        # rollers: u_x = 0 on x = 0, u_y = 0 on y = 0, u_z as exact on z = 0 (its bowl)
        held = np.stack([x < 1e-9, y < 1e-9, z < 1e-9], axis=1).ravel()
        free = ~held
        u = np.where(held, exact.ravel(), 0.0)
        rhs = load.ravel()[free] - (k @ u)[free]
        u[free] = factorize(k[free][:, free], "direct", np.zeros((int(free.sum()), 6)))(
            rhs[:, None]
        )[:, 0]
        u = u.reshape(-1, 3)
        assert np.abs(u - exact).max() < 1e-9 * np.abs(exact).max()
        # reactions balance the pull and the weight
        reaction = (k @ u.ravel() - load.ravel()).reshape(-1, 3)
        assert abs(reaction[:, 2].sum() + p * 1.0 - rho * g * length) < 1e-9 * rho * g * length


# --- reading at the lattice nodes ---------------------------------------------------------------


def test_quadratic_fields_interpolate_exactly_at_lattice_nodes_inside_and_outside():
    """Lattice nodes inside the mesh read a quadratic field exactly; nodes outside read it at
    the nearest point of the mesh (the cube: the clamped point), exactly."""
    nodes, tets = cube_tetrahedra(3, jitter=0.25)
    mesh = tet10.quadratic_mesh(nodes, tets)
    g = np.linspace(-0.2, 1.2, 8)
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    where = TetMesh(nodes, tets).locate(lattice)
    nearest = lattice.clip(0.0, 1.0)
    assert np.allclose(where.distance, np.linalg.norm(lattice - nearest, axis=1), atol=1e-14)

    def field(x: np.ndarray) -> np.ndarray:
        return np.stack([x[:, 0] ** 2 - x[:, 1], x[:, 0] * x[:, 2], 3 * x[:, 1] * x[:, 2]], axis=1)

    assert np.abs(tet10.interpolate(mesh, field(mesh.nodes), where) - field(nearest)).max() < 1e-13


def test_nested_start_carries_a_quadratic_field_exactly_to_the_split_mesh():
    """The next level's CG starts from the coarse field at the split mesh's nodes: a quadratic
    field is carried exactly (every child lies in its parent), and a mesh that is not the
    split gets no start."""
    nodes, tets = cube_tetrahedra(2, jitter=0.25)
    coarse = tet10.quadratic_mesh(nodes, tets)
    x_fine, t_fine = TetMesh(nodes, tets).refine()[:2]
    fine = tet10.quadratic_mesh(x_fine, t_fine)

    def field(x: np.ndarray) -> np.ndarray:
        return np.stack([x[:, 0] ** 2 - x[:, 1], x[:, 0] * x[:, 2], 3 * x[:, 1] * x[:, 2]], axis=1)

    nested = tet10.NestedStart()
    assert nested.guess(fine) is None
    nested.keep(coarse, np.stack([field(coarse.nodes), 2 * field(coarse.nodes)]))
    start = nested.guess(fine)
    assert start is not None and start.shape == (2, len(fine.nodes), 3)
    assert np.abs(start[0] - field(fine.nodes)).max() < 1e-13
    assert np.abs(start[1] - 2 * field(fine.nodes)).max() < 2e-13
    assert nested.guess(coarse) is None


def test_cg_started_at_the_answer_takes_no_iteration_and_from_near_it_fewer():
    """conjugate_gradients from x0: the exact solution stops at once; a start near it needs
    fewer iterations than zero for the same tolerance and lands on the same answer."""
    from fpm.fem.linear_solver import conjugate_gradients

    rng = np.random.default_rng(0)
    n = 60
    a = np.diag(np.linspace(1.0, 1e3, n))
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    a = q @ a @ q.T
    b = rng.normal(size=n)
    exact = np.linalg.solve(a, b)
    identity = np.array  # no preconditioner
    assert conjugate_gradients(a, b, identity, rtol=1e-10, x0=exact).iterations == 0
    cold = conjugate_gradients(a, b, identity, rtol=1e-10)
    warm = conjugate_gradients(a, b, identity, rtol=1e-10, x0=exact + 1e-4 * rng.normal(size=n))
    assert warm.converged and cold.converged and warm.iterations < cold.iterations
    assert np.abs(warm.x - exact).max() < 1e-6 * np.abs(exact).max()


def test_point_loads_are_consistent_and_reactions_balance_them_and_the_weight():
    """A point force goes to its tetrahedron's nodes with the same resultant and moment; solved
    on a clamped cube, the reactions balance the applied forces and the weight."""
    nodes, tets = cube_tetrahedra(2, size=0.1, jitter=0.2)
    mesh = tet10.quadratic_mesh(nodes, tets)
    points = np.array([[0.031, 0.052, 0.1], [0.07, 0.02, 0.045]])
    forces = np.array([[[0.0, 0.01, -0.02], [0.005, 0.0, 0.0]]])
    where = TetMesh(nodes, tets).locate(points)
    f = tet10.point_loads(mesh, forces, where)[0]
    assert np.allclose(f.sum(axis=0), forces[0].sum(axis=0), atol=1e-15)
    moment = np.cross(points, forces[0]).sum(axis=0)
    assert np.allclose(np.cross(mesh.nodes, f).sum(axis=0), moment, atol=1e-16)
    weight = tet10.body_forces(mesh, 1040.0, np.array([0.0, 0.0, -9.81]))
    total = f + weight
    k = tet10.stiffness_matrix(mesh, C)
    fixed = mesh.nodes[:, 2] < 1e-9
    free = np.repeat(~fixed, 3)
    u, residuals = solve_dirichlet(k, total.reshape(1, -1), free, mesh.nodes, "direct")
    reaction = (k @ u[0] - total.ravel()).reshape(-1, 3)
    assert np.abs(reaction[~fixed]).max() < 1e-9 * np.abs(total).max()
    scale = np.abs(total.sum(axis=0)).max()
    assert np.allclose(reaction[fixed].sum(axis=0), -total.sum(axis=0), atol=1e-10 * scale)


# --- the spec -----------------------------------------------------------------------------------


def cube_spec(n: int, n_tets: int | None = None, **more) -> dict:
    """The 0.1 m cube as a box lattice of n cells a side, the reference on a tetrahedral mesh
    of n_tets (default n) cells a side (as given: ``refine`` 0, point loads); E 5 kPa,
    nu 0.45, bottom fixed, own weight."""
    nodes, tets = cube_tetrahedra(n_tets or n, 0.1)
    return {
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1000.0},
        "geometry": {"type": "box", "size": [0.1, 0.1, 0.1], "nodes": [n + 1] * 3},
        "fixed": [{"face": "z-"}],
        "load_cases": [{"forces": [{"nearest": [0.05, 0.05, 0.1], "vector": [0, 0, -0.01]}]}],
        "fpm": {"gravity": [0.0, -5.0, -9.81]},
        "reference": {
            "mesh": {"nodes": nodes.tolist(), "tetrahedra": tets.tolist()},
            "refine": 0,
        },
        **more,
    }


def test_inverted_and_degenerate_tetrahedra_are_refused_naming_the_element():
    spec = cube_spec(2)
    tets = spec["reference"]["mesh"]["tetrahedra"]
    tets[5] = [tets[5][1], tets[5][0], tets[5][2], tets[5][3]]
    with pytest.raises(ValidationError) as e:
        fpm.load_problem(spec)
    error = e.value.errors()[0]
    assert error["loc"] == ("reference", "mesh", "tetrahedra", 5)
    assert "tetrahedron 5 is inverted" in error["msg"]
    spec = cube_spec(2)
    nodes = spec["reference"]["mesh"]["nodes"]
    a, b, c, _ = spec["reference"]["mesh"]["tetrahedra"][7]
    nodes.append([(nodes[a][i] + nodes[b][i] + nodes[c][i]) / 3 for i in range(3)])
    spec["reference"]["mesh"]["tetrahedra"].append([a, b, c, len(nodes) - 1])
    with pytest.raises(ValidationError) as e:
        fpm.load_problem(spec)
    error = e.value.errors()[0]
    last = len(spec["reference"]["mesh"]["tetrahedra"]) - 1
    assert error["loc"] == ("reference", "mesh", "tetrahedra", last)
    assert f"tetrahedron {last} is degenerate" in error["msg"]
    assert check_tetrahedra(np.zeros((4, 3)), np.array([[0, 1, 2, 9]]))[0][1] == 0


def test_solve_fem_uses_the_mesh_and_the_hash_covers_it():
    spec = cube_spec(2)
    problem = fpm.load_problem(spec)
    result = fpm.solve_fem(problem)
    assert result.element == "tet10"
    assert result.displacements.shape == (1, problem.n_nodes, 3)
    assert np.all(result.displacements[:, problem.fixed] == 0)
    assert fpm.FemResult.from_dict(result.to_dict()).element == "tet10"
    dumped = fpm.load_problem(spec).spec.model_dump()
    other = copy.deepcopy(dumped)
    other["reference"]["mesh"]["nodes"][0] = [0.0, 0.0, -1e-3]
    plain = copy.deepcopy(dumped)
    del plain["reference"]["mesh"], plain["reference"]["refine"]
    assert len({fem_hash(dumped), fem_hash(other), fem_hash(plain)}) == 3
    # a spec without a mesh dumps without the new fields (its identity is unchanged)
    assert set(fpm.load_problem(plain).spec.model_dump()["reference"]) == {
        "integration",
        "displacements",
    }


def hex27_under_weight(problem, rho: float, g: np.ndarray) -> np.ndarray:
    """(N, 3) the 27-node hexahedra's displacements at the lattice nodes under the consistent
    weight (3x3x3 Gauss points)."""
    hexahedra = problem.solid.elements()
    coords = problem.nodes[hexahedra]
    mesh = hex27_mesh(problem.nodes, hexahedra, problem.fixed)
    k = stiffness_matrix_27(mesh, coords, C).tocsr()
    share = np.zeros((len(hexahedra), 27))
    for point, w in zip(GAUSS_27, GAUSS_27_WEIGHTS, strict=True):
        n27, _ = quadratic_shape_functions(point)
        share += w * n27[None] * np.linalg.det(jacobians(coords, point))[:, None]
    f = np.bincount(mesh.hexahedra.ravel(), share.ravel(), len(mesh.nodes))[:, None] * rho * g
    free = np.repeat(~mesh.fixed, 3)
    u = np.zeros(f.size)
    u[free] = factorize(k[free][:, free], "direct", rigid_body_modes(mesh.nodes)[free])(
        f.ravel()[free][:, None]
    )[:, 0]
    return u.reshape(-1, 3)[: problem.n_nodes]


def test_cube_under_its_weight_agrees_with_hex27_and_converges():
    """The cube at nu 0.45 under its own weight (a smooth load, consistent in both elements),
    tetrahedra on the lattice's own grid (6 per cell) against 27-node hexahedra on the same
    grid: 1.2% apart at 3 cells, 0.77% at 4 (0.49% at 6): two quadratic elements converging to
    the same solid. (Point loads are left out: a point load's displacement is singular, and
    each element resolves it its own way.)"""
    g = np.array([0.0, -5.0, -9.81])
    gaps = []
    for n in (3, 4):
        spec = cube_spec(n)
        spec["load_cases"][0]["forces"][0]["vector"] = [0.0, 0.0, -1e-12]  # the weight only
        problem = fpm.load_problem(spec)
        u = fpm.solve_fem(problem).displacements[0]
        gaps.append(relative_gap(u, hex27_under_weight(problem, 1000.0, g)))
    assert gaps[1] < 0.01
    assert gaps[1] < 0.75 * gaps[0]


def test_voxel_reference_option_and_from_mesh_keep_the_tetrahedra():
    meshio = pytest.importorskip("meshio")
    from fpm.io.meshes import spec_from_mesh

    nodes, tets = cube_tetrahedra(2, 0.1, jitter=0.2)
    mesh = meshio.Mesh(nodes, [("tetra", tets)])
    kwargs = dict(
        fix=["face:z-"], forces=["nearest:0.05,0.05,0.1:0,0,-0.01"], youngs_modulus=5e3,
        poisson_ratio=0.45, spacing=0.025,
    )  # fmt: skip
    spec, notes = spec_from_mesh(mesh, **kwargs)
    assert len(spec["reference"]["mesh"]["tetrahedra"]) == len(tets)
    assert any("10-node" in note for note in notes)
    # One refinement: which element solves the reference is the point here, not how fine
    # (refine "auto" takes this jittered cube's point load to 274,625 FEM nodes, 85 s).
    spec["reference"]["refine"] = 1
    assert fpm.solve_fem(fpm.load_problem(spec)).element == "tet10"
    spec, _ = spec_from_mesh(mesh, voxel_reference=True, **kwargs)
    assert "reference" not in spec


def test_organ_reference_at_the_lattice_nodes_matches_scikit_fem():
    """The accuracy target: on a tetrahedral organ (the ellipsoid, E 5 kPa, nu 0.45, a
    probe force on top and its own weight, bottom centimetre fixed) made into a spec by
    ``spec_from_mesh``, the reference at the lattice nodes within 3% of an independent
    10-node solution (scikit-fem's ElementTetP2: its own assembly, weight, point load by its
    own shape functions at the same point, supports by the same box, values by its own
    probes). Measured: 1e-8 (the CG tolerance); the voxel staircase's hexahedra: 28% off."""
    skfem = pytest.importorskip("skfem")
    meshio = pytest.importorskip("meshio")
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    from bench.organ import ellipsoid_tetrahedra
    from fpm.io.meshes import spec_from_mesh

    nodes, tets = ellipsoid_tetrahedra(0.012)
    bottom = nodes[:, 2].min()
    spec, _ = spec_from_mesh(
        meshio.Mesh(nodes, [("tetra", tets)]),
        fix=[f"box:-1,-1,-1:1,1,{bottom + 0.01}"],
        forces=["nearest:0,0,0.04:0,0,-0.02"],
        youngs_modulus=5e3, poisson_ratio=0.45, density=1040.0, spacing=0.01,
        lattice="voxels",  # scikit-fem probes the lattice nodes: all inside the mesh
    )  # fmt: skip
    spec["fpm"]["gravity"] = [0.0, 0.0, -9.81]
    spec["reference"]["refine"] = 0  # the mesh as given, point loads: as scikit-fem has it
    problem = fpm.load_problem(spec)
    ours = fpm.solve_fem(problem).displacements[0]

    mesh = skfem.MeshTet(nodes.T.copy(), tets.T.copy())
    scalar = skfem.Basis(mesh, skfem.ElementTetP2(), intorder=4)
    vector = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP2()), intorder=4)
    k = skfem.asm(linear_elasticity(*lame_parameters(5e3, 0.45)), vector)

    @skfem.LinearForm
    def weight(v, w):
        return -1040.0 * 9.81 * v.value[2]

    f = skfem.asm(weight, vector)
    component = np.zeros((3, scalar.N), dtype=np.int64)  # scalar dof -> vector dof, per axis
    for c in range(3):
        component[c, scalar.nodal_dofs[0]] = vector.nodal_dofs[c]
        component[c, scalar.edge_dofs[0]] = vector.edge_dofs[c]
    # lattice nodes outside the mesh read at their nearest mesh point (located by fpm,
    # checked against geometry in the tests above), nudged into its tetrahedron
    where = TetMesh(nodes, tets).locate(problem.nodes)
    lam = (1 - 1e-6) * where.lam + 1e-6 / 4
    points = np.einsum("pa,pac->pc", lam, nodes[tets[where.element]])
    inside = where.distance == 0
    points[inside] = problem.nodes[inside]
    case = problem.load_cases[0].as_given()  # what the reference loads (fpm.loads "hat")
    at_load = scalar.probes(points[case.nodes].T)
    for c in range(3):
        f[component[c]] += at_load.T @ case.forces[:, c]
    box = np.asarray(spec["fixed"][0]["box"])
    x = scalar.doflocs.T
    held = np.all((x >= box[0] - 1e-3 * problem.h) & (x <= box[1] + 1e-3 * problem.h), axis=1)
    u = skfem.solve(*skfem.condense(k, f, D=np.concatenate([c[held] for c in component])))
    probes = scalar.probes(points.T)
    independent = np.stack([probes @ u[component[c]] for c in range(3)], axis=1)
    independent[problem.fixed] = 0.0
    assert relative_gap(ours, independent) < 0.03
    assert relative_gap(ours, independent) < 1e-6  # in fact the same to the CG tolerance


# --- the service: POST /v1/meshes and reference.mesh_id -----------------------------------------


def test_mesh_upload_and_reference_mesh_id_over_rest(api, redis, run_workers, sdk):
    spec = cube_spec(3, 2)
    mesh = spec["reference"].pop("mesh")
    # a bad mesh: 422 naming the element, nothing stored
    bad = copy.deepcopy(mesh)
    bad["tetrahedra"][3] = [bad["tetrahedra"][3][i] for i in (1, 0, 2, 3)]
    answer = api.post("/v1/meshes", json=bad)
    assert answer.status_code == 422, answer.text
    assert "tetrahedra.3" in [e["field"] for e in answer.json()["errors"]]
    assert "tetrahedron 3 is inverted" in answer.json()["detail"]
    assert redis.dbsize() == 0
    # content-addressed and idempotent: 201, then 200 with the same id (ints or floats alike)
    first = api.post("/v1/meshes", json=mesh)
    assert first.status_code == 201, first.text
    again = copy.deepcopy(mesh)
    again["nodes"] = [[float(x) for x in node] for node in again["nodes"]]
    second = api.post("/v1/meshes", json=again)
    assert second.status_code == 200 and second.json() == first.json()
    assert sdk.upload_mesh(mesh) == first.json()["id"]
    # an unknown mesh id is refused at submit, naming the field
    unknown = copy.deepcopy(spec)
    unknown["reference"]["mesh_id"] = "0" * 64
    answer = api.post("/v1/fem-references", json=unknown)
    assert answer.status_code == 422
    assert "reference.mesh_id" in [e["field"] for e in answer.json()["errors"]]
    # the worker solves the reference on the uploaded mesh: the inline mesh's answer
    spec["reference"]["mesh_id"] = first.json()["id"]
    submitted = api.post("/v1/fem-references", json=spec)
    assert submitted.status_code == 202, submitted.text
    run_workers()
    reference = api.get(submitted.headers["location"]).json()
    assert reference["status"] == "succeeded" and reference["element"] == "tet10"
    inline = fpm.solve_fem(fpm.load_problem(cube_spec(3, 2))).displacements
    assert relative_gap(np.asarray(reference["displacements"]), inline) < 1e-9
    # another mesh is another reference (the FEM hash covers the mesh)
    coarse = cube_spec(3, 1)["reference"]["mesh"]
    spec["reference"]["mesh_id"] = sdk.upload_mesh(coarse)
    assert api.post("/v1/fem-references", json=spec).status_code == 202


def test_mesh_upload_body_limit_is_its_own(api, settings):
    big = b'{"nodes": [' + b"[0.0, 0.0, 0.0], " * (settings.max_body_bytes // 16) + b"[0, 0, 0]]"
    answer = api.post("/v1/meshes", content=big, headers={"content-type": "application/json"})
    assert answer.status_code == 422  # past the spec routes' limit, within the mesh route's
    assert len(big) > settings.max_body_bytes
    huge = b" " * (settings.max_mesh_bytes + 1)
    answer = api.post("/v1/meshes", content=huge, headers={"content-type": "application/json"})
    assert answer.status_code == 413


def test_vtu_export_carries_the_tet10_reference(tmp_path):
    meshio = pytest.importorskip("meshio")
    from fpm.io.export import export

    problem = fpm.load_problem(cube_spec(2))
    record = {"stiffness": {"axis": 4.0, "face": 2.0, "body": 2.5}, "d": 0.15, "depth": 3}
    record["volume_stiffness"] = 1e3
    path = tmp_path / "lattice.vtu"
    path.write_bytes(export(problem, record, "vtu"))
    tet10_u = fpm.solve_fem(problem).displacements[0]
    hex8 = copy.deepcopy(cube_spec(2))
    del hex8["reference"]
    hex8_u = fpm.solve_fem(fpm.load_problem(hex8)).displacements[0]
    written = meshio.read(path).point_data["fem_displacement_1"]
    np.testing.assert_allclose(written, tet10_u, rtol=1e-9, atol=1e-12)
    assert relative_gap(written, hex8_u) > 1e-3  # not the hexahedra's
