"""A reference that says how far it is from converged (fpm/fem/refine.py, fpm/fem/levels.py,
fpm/fem/uniform_refinement.py, fpm/fem/loads.py, fpm/fem/samples.py):
uniform 1-to-8 refinement, the lattice's forces spread over the nodes' shares of the solid,
the convergence rate on a known solution, the auto loop and its estimate, the check of a voxel
reference, the spec field and the paper's examples."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

import fpm
from bench.tet_organ import organ_mesh
from fpm.fem import tet10
from fpm.fem.elasticity import constitutive_matrix, min_jacobian_determinants
from fpm.fem.levels import Mesh, converge, relative_change, summarise
from fpm.fem.linear_solver import factorize
from fpm.fem.loads import spread, tetrahedron_nodal_loads
from fpm.fem.refine import hexahedron_loads, tetrahedron_loads
from fpm.fem.samples import (
    Samples,
    hexahedron_surface_samples,
    hexahedron_volume_samples,
    lattice_spacing,
    lattice_surface,
    triangle_rule,
)
from fpm.fem.solution import FemError, FemResult
from fpm.fem.uniform_refinement import refine_hexahedra
from fpm.fitting.reference import check_reference
from fpm.model import tetrahedra
from fpm.model.tetrahedra import TetMesh
from store.hashing import fem_hash

ROOT = Path(__file__).resolve().parents[2]
KUHN = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]


def box_tetrahedra(cells: tuple[int, int, int], size: tuple[float, float, float], jitter=0.0):
    """A box [0, size] of cells[0] x cells[1] x cells[2] cubes, 6 tetrahedra each; interior
    nodes moved at random by up to ``jitter`` of a cell."""
    axes = [np.linspace(0, s, n + 1) for n, s in zip(cells, size, strict=True)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if jitter:
        spacing = np.asarray(size) / np.asarray(cells)
        inner = np.all((nodes > 1e-12) & (nodes < np.asarray(size) - 1e-12), axis=1)
        shift = np.random.default_rng(3).uniform(-1, 1, nodes.shape) * jitter * spacing
        nodes[inner] += shift[inner]
    nx, ny, nz = cells
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*map(np.arange, cells), indexing="ij"))
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    tets = corners[:, KUHN].reshape(-1, 4)
    flip = TetMesh(nodes, tets).volumes < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return nodes, tets


def small_box(**reference) -> dict:
    spec = json.loads((ROOT / "examples" / "small-box.json").read_text())
    spec["reference"] = reference
    return spec


# ------------------------------------------------------------------ refinement


@pytest.mark.parametrize("mesh", ["jittered box", "organ"])
def test_tetrahedra_split_into_8_conserve_volume_and_stay_positive(mesh):
    if mesh == "organ":
        nodes, tets = organ_mesh((5, 4, 3))
    else:
        nodes, tets = box_tetrahedra((3, 2, 2), (0.3, 0.2, 0.2), jitter=0.3)
    volume = TetMesh(nodes, tets).volumes
    x, t = nodes, tets
    for level in (1, 2):
        x, t, _ = TetMesh(x, t).refine()
        children = TetMesh(x, t).volumes
        assert len(t) == 8**level * len(tets)
        assert children.min() > 0
        # each parent's 8 children fill it exactly (and so the whole solid)
        per_parent = children.reshape(len(tets), -1).sum(axis=1)
        np.testing.assert_allclose(per_parent, volume, rtol=1e-12)
        assert np.array_equal(x[: len(nodes)], nodes)  # old nodes first, unmoved

    # a new node is held when both ends of its edge are: the held region stays the same
    fixed = nodes[:, 2] < 0.3 * nodes[:, 2].max()
    x1, t1, held = TetMesh(nodes, tets).refine(fixed)
    assert np.array_equal(held[: len(nodes)], fixed)
    ends = np.unique(np.sort(tets[:, [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]], axis=2)
                     .reshape(-1, 2), axis=0)  # fmt: skip
    mids = {tuple(np.round((nodes[a] + nodes[b]) / 2, 12)): fixed[a] & fixed[b] for a, b in ends}
    new = zip(x1[len(nodes) :], held[len(nodes) :], strict=True)
    assert all(mids[tuple(np.round(p, 12))] == h for p, h in new)

    # children are no flatter than their parents by much: the shortest diagonal keeps shape
    def quality(xx, tt):
        c = xx[tt]
        edges = np.linalg.norm(c[:, [0, 1, 0, 0, 1, 2]] - c[:, [1, 2, 2, 3, 3, 3]], axis=2)
        return TetMesh(xx, tt).volumes / edges.max(axis=1) ** 3

    assert quality(x, t).min() > 0.3 * quality(nodes, tets).min()


def test_hexahedra_split_into_8_keep_lattice_nodes_and_held_faces():
    problem = fpm.load_problem(small_box())
    hexahedra = problem.solid.elements()
    x, hx, held = refine_hexahedra(problem.nodes, hexahedra, problem.fixed)
    assert len(hx) == 8 * len(hexahedra) and len(x) == 7**3
    assert np.array_equal(x[: problem.n_nodes], problem.nodes)
    assert min_jacobian_determinants(x[hx]).min() > 0
    np.testing.assert_allclose(sum(np.prod(np.ptp(x[h], axis=0)) for h in hx), 0.03**3, rtol=1e-12)
    bottom = np.isclose(x[:, 2], 0.0)
    assert np.array_equal(held, bottom)  # the held face z- stays held, nothing else


# ------------------------------------------------------------------ loads


def box_problem(forces: list[tuple[list[float], list[float]]]) -> fpm.Problem:
    """0.1 m box, 5 x 5 x 5 lattice nodes (h = 25 mm), one load case per (point, force)."""
    return fpm.load_problem(
        {
            "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040},
            "geometry": {"type": "box", "size": [0.1, 0.1, 0.1], "nodes": [5, 5, 5]},
            "fixed": [{"face": "z-"}],
            "load_cases": [
                {"name": f"case {i}", "forces": [{"at": at, "vector": f}]}
                for i, (at, f) in enumerate(forces)
            ],
        }
    )


LOADS = [
    ([0.05, 0.05, 0.1], [0.3, -0.2, -1.0]),  # top face, oblique
    ([0.05, 0.0, 0.1], [0.0, 0.0, -1.0]),  # an edge of the box, pressed
    ([0.1, 0.1, 0.1], [0.0, 0.0, -1.0]),  # a corner, pressed
    ([0.05, 0.05, 0.05], [1.0, 0.5, 0.0]),  # an interior node: a body load on its cell
    ([0.1, 0.05, 0.075], [0.0, 1.0, 0.2]),  # a side face, sheared
]


def moments(points: np.ndarray, forces: np.ndarray) -> np.ndarray:
    return np.cross(points, forces).sum(axis=-2)


@pytest.mark.parametrize("element", ["tet10", "hex8"])
def test_the_spread_load_sums_to_the_lattice_force_and_its_moment(element):
    problem = box_problem(LOADS)
    forces = np.stack([c.dense(problem.n_nodes) for c in problem.load_cases])
    if element == "tet10":
        nodes, tets = box_tetrahedra((4, 4, 4), (0.1, 0.1, 0.1))
        mesh = tet10.quadratic_mesh(*TetMesh(nodes, tets).refine()[:2])
        where = TetMesh(mesh.nodes[: mesh.n_corners], mesh.corners).locate(problem.nodes)
        nodal = tetrahedron_loads(problem, forces)(mesh, where)
        positions = mesh.nodes
    else:
        hexahedra = problem.solid.elements()
        x, hx, _ = refine_hexahedra(problem.nodes, hexahedra)
        surface = lattice_surface(hexahedra, problem.n_nodes)
        nodal = hexahedron_loads(problem, x, hx, forces, surface)
        positions = x
    for case, (at, f) in enumerate(LOADS):
        f = np.asarray(f)
        np.testing.assert_allclose(nodal[case].sum(axis=0), f, atol=1e-13)
        expected = np.cross(np.asarray(at), f)
        got = moments(positions, nodal[case])
        scale = np.linalg.norm(f) * problem.h
        if case in (0, 3, 4):  # on a face, inside: exactly the lattice force's moment
            np.testing.assert_allclose(got, expected, atol=1e-10 * scale)
        else:  # an edge, a corner: as near as weights that stay positive allow, the
            # resultant's line within h/2 of the node (its hat reaches h from it)
            assert np.linalg.norm(got - expected) < 0.5 * scale
        # spread: the loaded node takes a part only, its neighbours the rest
        node = problem.load_cases[case].nodes[0]
        assert np.linalg.norm(nodal[case][np.argmin(np.linalg.norm(positions - at, axis=1))]) < (
            0.7 * np.linalg.norm(f)
        ), node


def test_a_uniform_tractions_nodal_forces_spread_back_to_that_traction():
    """The hats are a partition of unity: the consistent nodal forces of a uniform traction t
    on the top face (t h^2 on its inner nodes, half on its edges, a quarter at its corners)
    come back as t itself wherever only inner nodes' hats reach (at least h from the face's
    edges), every sample carrying t times its area."""
    problem = box_problem(LOADS[:1])  # its loads are not used
    x, h = problem.nodes, problem.h
    top = np.flatnonzero(np.isclose(x[:, 2], 0.1))
    on_edge = np.isclose(x[top, 0], 0.0) | np.isclose(x[top, 0], 0.1)
    on_edge2 = np.isclose(x[top, 1], 0.0) | np.isclose(x[top, 1], 0.1)
    t = np.array([0.2, -0.1, -1.0])  # Pa
    forces = np.zeros((1, problem.n_nodes, 3))
    forces[0, top] = (
        t * h**2 * np.where(on_edge, 0.5, 1.0)[:, None] * np.where(on_edge2, 0.5, 1.0)[:, None]
    )
    hexahedra = problem.solid.elements()
    surface = lattice_surface(hexahedra, problem.n_nodes)
    at_nodes = Samples(x, np.ones(len(x)), np.zeros(len(x), dtype=np.int64), np.zeros((len(x), 3)))
    spacing = lattice_spacing(x, hexahedra)
    np.testing.assert_allclose(spacing, [h, h, h])
    out = spread(
        x, surface, spacing, forces,
        hexahedron_surface_samples(x, hexahedra, x[top], h),
        lambda: hexahedron_volume_samples(x, hexahedra, x[top], h),
        at_nodes,
    )  # fmt: skip
    assert set(out.kinds.values()) == {"traction"}
    np.testing.assert_allclose(out.forces.sum(axis=1)[0], t * 0.1**2, rtol=1e-12)
    points, where = np.unique(np.round(out.samples.points, 12), axis=0, return_inverse=True)
    load = np.zeros((len(points), 3))
    np.add.at(load, where.ravel(), out.forces[0])
    inner = np.all((points[:, :2] > h + 1e-9) & (points[:, :2] < 0.1 - h - 1e-9), axis=1)
    inner &= np.isclose(points[:, 2], 0.1)
    assert inner.sum() > 100
    samples = hexahedron_surface_samples(x, hexahedra, x[top], h)
    sample_area = dict(zip(map(tuple, np.round(samples.points, 12)), samples.weights, strict=True))
    expected = np.array([sample_area[tuple(p)] for p in points[inner]])[:, None] * t
    np.testing.assert_allclose(load[inner], expected, rtol=1e-9, atol=1e-15)


def organ_spec(cells: tuple[int, int, int], h: float = 0.01) -> dict:
    """The organ of bench/tet_organ.py as a voxel lattice (cells whose centre lies in the
    ellipsoid) with its tetrahedra as the reference, held below z = -25 mm, pressed on top
    and pulled sideways."""
    nodes, tets = organ_mesh(cells)
    lo = nodes.min(axis=0)
    counts = np.ceil(np.ptp(nodes, axis=0) / h).astype(int)
    centres = lo + h * (np.stack(np.meshgrid(*map(np.arange, counts), indexing="ij"), -1) + 0.5)
    inside = ((centres / np.array([0.07, 0.045, 0.035])) ** 2).sum(axis=-1) < 1
    return {
        "material": {"youngs_modulus": 5e3, "poisson_ratio": 0.45, "density": 1040},
        "geometry": {
            "type": "voxels",
            "occupancy": inside.tolist(),
            "spacing": [h, h, h],
            "origin": lo.tolist(),
        },
        "fixed": [{"box": [[-1, -1, -1], [1, 1, -0.025]]}],
        "load_cases": [
            {"name": "press", "forces": [{"nearest": [0, 0, 0.035], "vector": [0, 0, -0.02]}]},
            {"name": "pull", "forces": [{"nearest": [0.07, 0, 0], "vector": [0.01, 0, 0]}]},
        ],
        "reference": {"mesh": {"nodes": nodes.tolist(), "tetrahedra": tets.tolist()}},
    }


def test_spread_loads_on_a_curved_organ_keep_the_resultant():
    spec = organ_spec((5, 4, 3))
    nodes = np.array(spec["reference"]["mesh"]["nodes"])
    tets = np.array(spec["reference"]["mesh"]["tetrahedra"])
    problem = fpm.load_problem(spec)
    given = [c.as_given() for c in problem.load_cases]  # what the reference loads
    forces = np.stack([c.dense(problem.n_nodes) for c in given])
    mesh = tet10.quadratic_mesh(nodes, tets)
    where = TetMesh(nodes, tets).locate(problem.nodes)
    nodal = tetrahedron_loads(problem, forces)(mesh, where)
    for case in range(2):
        np.testing.assert_allclose(nodal[case].sum(axis=0), forces[case].sum(axis=0), atol=1e-14)
        x = problem.nodes[given[case].nodes[0]]
        f = forces[case].sum(axis=0)
        couple = moments(mesh.nodes, nodal[case]) - np.cross(x, f)
        # the lattice node lies off the mesh's surface: at most a couple of |f| times that gap
        assert np.linalg.norm(couple) < np.linalg.norm(f) * problem.h


# ------------------------------------------------------------------ convergence


def test_refined_tetrahedra_converge_at_the_expected_rate_on_a_bar_with_a_known_answer():
    """A bar (0.2 x 0.1 x 0.1 m) held at x = 0 and loaded by tractions on its other faces: the
    exact answer is u = grad phi, phi = s a exp(x/a) cos(y/a) (harmonic, so it solves Navier's
    equations with no body force for any E and nu), with the tractions 2 mu Hess(phi) n. The
    10-node tetrahedra on the uniformly refined mesh converge to it at the expected rate: h^3
    over all their nodes (the quadratic element's L2 rate; measured 2.9, 3.0, 3.3 over levels
    0-3), about h^2.5 at the coarse mesh's nodes where the fit reads it (2.5, 2.4, 2.6); and
    the change between two levels, the refined reference's estimated error, bounds the finer
    level's true error."""
    e, nu, a, s = 5e3, 0.45, 0.1, 1e-3
    mu = e / (2 * (1 + nu))
    c = constitutive_matrix(e, nu)

    def exact(x):
        g = np.exp(x[:, 0] / a)
        return s * np.stack([g * np.cos(x[:, 1] / a), -g * np.sin(x[:, 1] / a), 0 * g], axis=1)

    def traction(x, n):
        g = np.exp(x[:, 0] / a) / a
        cy, sy = np.cos(x[:, 1] / a), np.sin(x[:, 1] / a)
        hess = np.zeros((len(x), 3, 3))
        hess[:, 0, 0], hess[:, 0, 1] = g * cy, -g * sy
        hess[:, 1, 0], hess[:, 1, 1] = -g * sy, -g * cy
        return 2 * mu * s * np.einsum("qij,qj->qi", hess, n)

    nodes, tets = box_tetrahedra((2, 1, 1), (0.2, 0.1, 0.1))
    lattice = nodes.copy()  # read at the coarse mesh's nodes
    errors, everywhere, solutions = [], [], []
    x, t = nodes, tets
    st, share = triangle_rule(8)
    for _ in range(3):
        mesh = tet10.quadratic_mesh(x, t)
        faces, owner = TetMesh(x, t).boundary
        tri = x[faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = np.linalg.norm(normal, axis=1) / 2
        normal /= 2 * area[:, None]
        loaded = np.flatnonzero(tri[:, :, 0].max(axis=1) > 1e-12)  # not the held face x = 0
        ab = (tri[loaded, 1] - tri[loaded, 0])[:, None]
        ac = (tri[loaded, 2] - tri[loaded, 0])[:, None]
        points = (tri[loaded, 0][:, None] + st[None, :, :1] * ab + st[None, :, 1:] * ac).reshape(
            -1, 3
        )
        element = np.repeat(owner[loaded], len(st))
        lam = tetrahedra.barycentric(x[t[element]], points)
        weights = (area[loaded][:, None] * share[None]).ravel()
        samples = Samples(points, weights, element, lam)
        load = traction(points, np.repeat(normal[loaded], len(st), axis=0)) * weights[:, None]
        f = tetrahedron_nodal_loads(mesh.elements, len(mesh.nodes), samples, load[None])[0]
        held = mesh.nodes[:, 0] < 1e-12
        k = tet10.stiffness_matrix(mesh, c).tocsr()
        u = np.where(held[:, None], exact(mesh.nodes), 0.0).ravel()
        free = np.repeat(~held, 3)
        rhs = f.ravel()[free] - (k @ u)[free]
        u[free] = factorize(k[free][:, free], "direct", np.zeros((int(free.sum()), 6)))(
            rhs[:, None]
        )[:, 0]
        where = TetMesh(x, t).locate(lattice)
        u_lattice = tet10.interpolate(mesh, u.reshape(-1, 3), where)
        solutions.append(u_lattice[None])
        truth = exact(lattice)
        errors.append(relative_change(truth[None], u_lattice[None])[0])
        everywhere.append(relative_change(exact(mesh.nodes)[None], u.reshape(1, -1, 3))[0])
        x, t, _ = TetMesh(x, t).refine()

    def rates(e):
        return np.log2(np.array(e[:-1]) / np.array(e[1:]))

    assert errors[-1] < 0.2  # %
    assert rates(everywhere).min() > 2.7, everywhere
    assert rates(errors).min() > 2.2, errors
    for level in range(1, 3):
        change = relative_change(solutions[level - 1], solutions[level])[0]
        assert errors[level] <= change <= 1.5 * errors[level - 1], (level, errors, change)


# ------------------------------------------------------------------ the auto loop


def fake_levels(changes: list[float], nodes: list[int], iterations: int | None = None) -> Mesh:
    """Level 0 of a sequence of meshes whose solutions change by ``changes`` (%) from one level
    to the next (a 2-node field, one load case), level l having ``nodes[l]`` FEM nodes and
    solved by ``iterations`` CG iterations (None: a direct solve)."""
    solved: list[int] = []

    def level(k: int) -> Mesh:
        scale = 1 + sum(c / 100 for c in changes[:k])  # |u_k - u_k-1| / |u_k|: changes[k-1] / scale

        def solve() -> FemResult:
            solved.append(k)
            u = np.zeros((1, 2, 3))
            u[0, :, 0] = scale
            return FemResult(
                np.zeros((2, 3)),
                u,
                [0.0],
                ["case"],
                "direct" if iterations is None else "amg",
                loads="spread",
                iterations=[] if iterations is None else [iterations],
            )

        return Mesh(k, nodes[k], solve, lambda: level(k + 1))

    first = level(0)
    first.solved = solved  # type: ignore[attr-defined]
    return first


def test_refine_auto_stops_under_1_percent_and_reports_the_last_change():
    # changes 8, 3, 0.5, 0.1 %: stops at level 3, the first change under 1%
    first = fake_levels([8.0, 3.0, 0.5, 0.1], [100, 800, 6400, 51200, 409600])
    levels, notes = converge(first, "auto", 10**6)
    assert [level.refinements for level in levels] == [0, 1, 2, 3] and notes == []
    result = summarise(levels, notes)
    assert result.refinements == 3 and result.estimated_error == pytest.approx([0.5 / 1.115])
    assert [level["change"][0] for level in result.levels[1:]] == pytest.approx(
        [8 / 1.08, 3 / 1.11, 0.5 / 1.115]
    )
    # or at the node budget: level 3 would have 51,200 nodes
    first = fake_levels([8.0, 3.0, 0.5, 0.1], [100, 800, 6400, 51200, 409600])
    levels, notes = converge(first, "auto", 50_000)
    assert [level.refinements for level in levels] == [0, 1, 2]
    result = summarise(levels, notes)
    assert result.estimated_error == pytest.approx([3 / 1.11]) and result.refinements == 2
    assert "51,200 FEM nodes, over reference.node_budget (50,000)" in result.notes[0]
    # a number of refinements: that level and the one before, nothing else solved
    first = fake_levels([8.0, 3.0, 0.5, 0.1], [100, 800, 6400, 51200, 409600])
    levels, _ = converge(first, 2, 10**6)
    assert first.solved == [1, 2]  # type: ignore[attr-defined]
    assert summarise(levels, []).estimated_error == pytest.approx([3 / 1.11])


def test_refine_tells_each_level_as_it_starts():
    told: list[dict] = []
    first = fake_levels([8.0, 3.0, 0.5, 0.1], [100, 800, 6400, 51200, 409600])
    levels, _ = converge(first, "auto", 10**6, progress=told.append)
    assert [t["level"] for t in told] == [0, 1, 2, 3]
    assert [t["fem_nodes"] for t in told] == [100, 800, 6400, 51200]
    changes = [max(level["change"]) for level in summarise(levels, []).levels[1:3]]
    assert [t["last_change"] for t in told[:2]] == [None, None]  # no change before two levels
    assert [t["last_change"] for t in told[2:]] == pytest.approx(changes)


def test_refine_auto_stops_before_a_level_whose_cg_iterations_make_it_too_costly():
    """The work of a level is its nodes times the CG iterations per case the level before
    needed: a mesh of slivers (examples/lobe.vtu: 717 iterations) is not refined to a level
    that would cost more than the node budget of a well-shaped one; an explicit number of
    refinements is solved whatever it costs."""
    nodes = [10_000, 80_000, 640_000]
    # well-shaped: 60 iterations, level 1 costs 80,000 x 60 / 100 = 48,000 nodes' worth
    first = fake_levels([0.5, 0.1], nodes, iterations=60)
    levels, notes = converge(first, "auto", 400_000)
    assert [level.refinements for level in levels] == [0, 1] and notes == []
    # slivers: 700 iterations, level 1 costs 560,000 nodes' worth
    first = fake_levels([0.5, 0.1], nodes, iterations=700)
    levels, notes = converge(first, "auto", 400_000)
    assert [level.refinements for level in levels] == [0] and first.solved == [0]  # type: ignore[attr-defined]
    assert "80,000 FEM nodes, and at the 700 CG iterations" in notes[0]
    assert "as much as 560,000 nodes, over reference.node_budget (400,000)" in notes[0]
    result = summarise(levels, notes)
    assert result.estimated_error is None and result.levels[0]["iterations"] == [700]
    assert result.notes[-1] == "reference.refine: one level only, so its error is not estimated"
    # a larger budget refines it; a number of refinements asks for that level outright
    assert len(converge(fake_levels([0.5, 0.1], nodes, iterations=700), "auto", 600_000)[0]) == 2
    first = fake_levels([0.5, 0.1], nodes, iterations=700)
    assert [level.refinements for level in converge(first, 1, 400_000)[0]] == [0, 1]


def test_a_refined_reference_keeps_its_estimate_through_the_store():
    result = fpm.solve_fem(fpm.load_problem(small_box(refine=1)))
    assert result.estimated_error is not None and result.loads == "spread"
    again = FemResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert again.estimated_error == result.estimated_error and again.levels == result.levels
    old = {
        k: v
        for k, v in result.to_dict().items()
        if k not in ("estimated_error", "refinements", "loads", "levels", "notes")
    }
    before = FemResult.from_dict(old)  # stored before the estimate existed
    assert before.estimated_error is None and before.refinements == 0 and before.loads == "nodal"
    assert before.levels == [] and before.notes == []


def test_refine_auto_stops_at_the_node_budget_and_says_so():
    result = fpm.solve_fem(fpm.load_problem(small_box(refine="auto", node_budget=1000)))
    assert [level["fem_nodes"] for level in result.levels] == [64, 343]
    assert result.refinements == 1 and result.estimated_error == result.levels[1]["change"]
    assert "node_budget" in result.notes[0] and "2,197" in result.notes[0]
    # a number of refinements the budget cannot hold is refused, naming the fields
    with pytest.raises(FemError, match="reference.refine: 2 refinement.*node_budget"):
        fpm.solve_fem(fpm.load_problem(small_box(refine=4, node_budget=1000)))


def test_refine_n_is_level_n_with_the_change_from_n_minus_1():
    two = fpm.solve_fem(fpm.load_problem(small_box(refine=2)))
    one = fpm.solve_fem(fpm.load_problem(small_box(refine=1)))
    assert [level["refinements"] for level in two.levels] == [1, 2]
    assert np.array_equal(two.levels[0]["change"] or [], [])
    np.testing.assert_allclose(
        two.estimated_error, relative_change(one.displacements, two.displacements), rtol=1e-9
    )


# ------------------------------------------------------------------ voxel references


def test_the_voxel_check_flags_a_press_on_a_single_voxel():
    problem = fpm.load_problem(small_box())  # refine not given: the hexahedra are checked
    result = fpm.solve_fem(problem)
    plain = fpm.solve_fem(fpm.load_problem(small_box(refine=0)))
    assert np.array_equal(result.displacements, plain.displacements)  # the same reference
    assert plain.estimated_error is None and result.refinements == 0
    assert min(result.estimated_error) > 5.0  # a point press on a 3-cell box: 40%
    warnings = check_reference(problem, result)
    assert len([w for w in warnings if "estimated error" in w]) == len(problem.load_cases)
    assert "not resolve this load" in warnings[0] and "reference.refine" in warnings[0]
    # 6 cells a side: one node pressed 22%, the whole top face (a uniform traction) 3.4%
    spec = small_box()
    spec["geometry"]["nodes"] = [7, 7, 7]
    spec["load_cases"] = [
        {"name": "press", "forces": [{"at": [0.015, 0.015, 0.03], "vector": [0, 0, -0.05]}]},
        {"name": "top", "forces": [{"face": "z+", "vector": [0, 0, -0.05], "distribute": True}]},
    ]
    press, top = fpm.solve_fem(fpm.load_problem(spec)).estimated_error
    assert press > 15.0 and top < 5.0


def test_the_paper_examples_keep_the_8_node_reference_they_name():
    for name in ("a", "b"):
        spec = json.loads((ROOT / "examples" / f"paper-material-{name}.json").read_text())
        assert spec["reference"] == {"integration": "full", "refine": 0}
        problem = fpm.load_problem(spec)
        result = fpm.solve_fem(problem)
        assert result.estimated_error is None and result.levels == [] and result.loads == "nodal"
        unnamed = copy.deepcopy(spec)
        del unnamed["reference"]["refine"]
        checked = fpm.solve_fem(fpm.load_problem(unnamed))  # the check leaves it bit for bit
        assert np.array_equal(checked.displacements, result.displacements)


# ------------------------------------------------------------------ the spec


@pytest.mark.parametrize(
    ("refine", "fragment"),
    [(7, "less than or equal to 6"), (-1, "greater than or equal to 0"), ("fast", "auto"),
     (True, "number of refinements"), (1.5, "")],
)  # fmt: skip
def test_a_bad_refine_names_the_field(refine, fragment):
    with pytest.raises(ValidationError) as caught:
        fpm.load_problem(small_box(refine=refine))
    errors = caught.value.errors()
    assert all(e["loc"][:2] == ("reference", "refine") for e in errors), errors
    assert fragment in str(caught.value)


def test_refine_is_refused_where_nothing_is_refined():
    nh = small_box(refine=2)
    nh["material"]["model"] = "neo-hookean"
    with pytest.raises(ValidationError) as caught:
        fpm.load_problem(nh)
    assert caught.value.errors()[0]["loc"] == ("reference", "refine")
    problem = fpm.load_problem(small_box())
    supplied = small_box(refine="auto", displacements=np.zeros((2, 64, 3)).tolist())
    assert problem.n_nodes == 64
    with pytest.raises(ValidationError, match="supplied reference"):
        fpm.load_problem(supplied)
    with pytest.raises(ValidationError) as caught:
        fpm.load_problem(small_box(node_budget=10))
    assert caught.value.errors()[0]["loc"] == ("reference", "node_budget")


def test_the_refinement_is_part_of_the_references_identity():
    dumps = [
        fpm.load_problem(small_box(**r)).spec.model_dump(mode="json")
        for r in ({}, {"refine": 0}, {"refine": "auto"}, {"refine": "auto", "node_budget": 5000})
    ]
    assert "refine" not in dumps[0]["reference"]  # not given: left out, the old spelling
    assert len({fem_hash(d) for d in dumps}) == 4


@pytest.mark.redis
def test_rest_refuses_a_bad_refine_with_422_and_queues_nothing(api, redis):
    for bad in ({"refine": "always"}, {"refine": 2, "node_budget": 5}):
        response = api.post("/v1/calibrations", json=small_box(**bad))
        assert response.status_code == 422, response.text
        fields = [e["field"] for e in response.json()["errors"]]
        assert any(f.startswith("reference.") for f in fields), fields
    nh = small_box(refine=1)
    nh["material"]["model"] = "neo-hookean"
    response = api.post("/v1/fem-references", json=nh)
    assert response.status_code == 422, response.text
    assert "reference.refine" in [e["field"] for e in response.json()["errors"]]
    assert redis.dbsize() == 0


def test_fpmcal_fem_says_each_level_as_it_starts(tmp_path, capsys):
    from fpmcal.cli import main
    from tests.helpers_fpm import box_spec

    spec = box_spec((3, 3, 4), 0.01, fpm_settings={"stiffness": "families+volume"})
    spec["reference"] = {"refine": 1}
    path = tmp_path / "box.json"
    path.write_text(json.dumps(spec))
    assert main(["fem", str(path), "-o", str(tmp_path / "fem.json")]) == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("FEM reference:")]
    assert lines == [
        "FEM reference: refinement level 0, 36 FEM nodes",
        "FEM reference: refinement level 1, 175 FEM nodes",
    ]
