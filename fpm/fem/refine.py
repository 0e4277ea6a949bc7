"""A reference that says how far it is from converged: uniform refinement and its estimate.

The FEM reference is a discretisation too: 10-node tetrahedra on a surface-quality mesh, or
8-node hexahedra on the lattice's own voxels, can be several percent from the solid they stand
for under a press. ``reference.refine`` (:class:`fpm.model.spec.ReferenceSettings`) solves it
again on uniformly refined meshes and reports, per load case, the *estimated error*: the
relative change at the lattice nodes from the last level to the one before,
``sum_i |u_l - u_l-1| / sum_i |u_l|`` over the lattice nodes (the relative discrepancy's
measure), in %.

- **Refinement.** A tetrahedron is split into 8 (Bey's red refinement: a corner tetrahedron at
  each corner, the inner octahedron cut along its shortest diagonal into 4), a hexahedron into
  8 by its own trilinear map; nodes at the middle of every edge (and of every face and
  hexahedron), shared by neighbours, the coarse mesh's nodes first, so the lattice's nodes keep
  their numbers in a refined voxel mesh (:meth:`fpm.model.tetrahedra.TetMesh.refine`,
  :mod:`fpm.fem.uniform_refinement`). Volume is
  conserved exactly, and every child is positive (tests/core/test_refine.py).
- **Loads.** A point load's displacement does not converge under refinement, so every level
  applies a lattice nodal force as a load on that node's share of the solid
  (:mod:`fpm.fem.loads`: a traction on the surface within its hat, the lattice's trilinear
  shape function of that node, or a body load on the volume within it), sampled the same way
  at every level.
- **Supports.** On tetrahedra, by position at every level (:func:`fpm.fem.tet10.fixed_nodes`):
  each level holds the region the spec's selectors name as well as its mesh resolves it, so a
  held region whose boundary no mesh face follows converges only as its staircase does (first
  order); a selector's plane on a layer of the mesh's nodes is held exactly at every level. On
  hexahedra (the lattice's own cells) a refined node is held when every lattice node spanning
  it is, exactly the lattice's held region. Where a held region meets the free surface the
  solid has a singular line, and the reference converges more slowly the more obliquely they
  meet (bench/tet_organ.py).
- **Levels** (:func:`fpm.fem.levels.converge`). ``refine: n`` solves levels n - 1 and n (each
  one refinement finer) and hands back level n with the change between them; ``refine: "auto"``
  (the default for a tetrahedral mesh) solves levels 0, 1, 2, ... until the change is below
  :data:`~fpm.fem.levels.TOLERANCE` (1%) in every load case or the next level would have more
  FEM nodes than ``reference.node_budget`` (:data:`~fpm.fem.levels.DEFAULT_NODE_BUDGET`), or
  would cost as much as that many nodes of a well-shaped mesh (its nodes times the CG
  iterations the level before needed, over :data:`~fpm.fem.levels.WORK_ITERATIONS`), and hands
  back the last level with its last change. On tetrahedra each level's CG starts from the
  level before's field (:class:`~fpm.fem.tet10.NestedStart`: nested iteration).
  ``refine: "check"`` (the default for hexahedra) keeps the 8-node reference
  on the voxels as it is, nodal point loads and all (bit for bit), and estimates its error by
  one refinement with the spread loads: the change between the two is how far the reference
  fitted against is from a solid that resolves its loads; a press on a single voxel shows here
  as a large change. The check runs on lattices whose refined mesh has at most
  :data:`CHECK_NODES` nodes unless ``refine`` names it. ``refine: 0`` is the reference as it was:
  the mesh as given, point loads, no estimate (the paper's examples name it).
- **Reported**: :attr:`FemResult.estimated_error` per load case (then validation case), the
  refinements used, each level's FEM nodes, change and seconds (:attr:`FemResult.levels`) and
  notes (a level the budget refused); a calibration warns above
  :data:`~fpm.fem.levels.WARN_ERROR` (5%).

Units: m, N, Pa; changes in %.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..model.hexahedron import NATURAL
from ..model.problem import Problem, resolved_refine
from ..model.tetrahedra import Location, TetMesh
from .assembly import body_forces
from .levels import DEFAULT_NODE_BUDGET, Mesh, Progress, checked, converge, summarise
from .linear_solver import choose_method
from .loads import hexahedron_nodal_loads, spread, tetrahedron_nodal_loads
from .materials import hexahedron_densities, hexahedron_stiffness
from .samples import (
    Samples,
    hexahedron_surface_samples,
    hexahedron_volume_samples,
    lattice_spacing,
    lattice_surface,
    tetrahedron_surface_samples,
    tetrahedron_volume_samples,
)
from .solution import FemError, FemResult, solve_dirichlet
from .tet10 import NestedStart, Tet10Mesh, tet10_reference
from .uniform_refinement import refine_hexahedra

CHECK_NODES = 60_000
"""The default check of a hexahedral reference (``refine`` not given) runs when its refined mesh
has at most this many nodes (a lattice of about 7,500 nodes: a second or two); name
``refine: "check"`` to check a larger one (up to the node budget)."""


# ------------------------------------------------------------------ tetrahedra


def tetrahedron_loads(
    problem: Problem, forces: np.ndarray
) -> Callable[[Tet10Mesh, Location], np.ndarray]:
    """The ``loads`` of :func:`fpm.fem.tet10.tet10_reference` that spreads the lattice's
    ``forces`` (L, N, 3), N, over the nodes' shares of the tetrahedral solid."""
    hexahedra = problem.solid.elements()
    assert hexahedra is not None
    surface = lattice_surface(hexahedra, problem.n_nodes)
    lattice = problem.nodes
    spacing = lattice_spacing(lattice, hexahedra)
    h = float(spacing.max())  # the samples reach the hats and lie h / 8 apart

    def loads(mesh: Tet10Mesh, where: Location) -> np.ndarray:
        tet = TetMesh(mesh.nodes[: mesh.n_corners], mesh.corners)
        loaded = lattice[np.any(forces != 0, axis=(0, 2))]
        at_nodes = Samples(lattice, np.ones(len(lattice)), where.element, where.lam)
        spreaded = spread(
            lattice,
            surface,
            spacing,
            forces,
            tetrahedron_surface_samples(tet, loaded, h),
            lambda: tetrahedron_volume_samples(tet, loaded, h),
            at_nodes,
        )
        return tetrahedron_nodal_loads(
            mesh.elements, len(mesh.nodes), spreaded.samples, spreaded.forces
        )

    return loads


def refined_tet_reference(
    problem: Problem,
    nodes: np.ndarray,
    tets: np.ndarray,
    method: str = "auto",
    progress: Progress | None = None,
) -> FemResult:
    """The 10-node tetrahedral reference on ``tets`` refined as ``reference.refine`` says
    (module docstring); ``"check"`` solves the mesh as given with point loads and estimates
    its error by one refinement with spread loads. ``progress``: as :func:`converge`'s."""
    refine = resolved_refine(problem.spec)
    budget = problem.spec.reference.node_budget or DEFAULT_NODE_BUDGET
    forces = np.stack([case.as_given().dense(problem.n_nodes) for case in problem.all_cases])
    loads = tetrahedron_loads(problem, forces)
    nested = NestedStart()  # each level's CG starts from the level before's field

    def level(refinements: int, x: np.ndarray, t: np.ndarray) -> Mesh:
        # Supports by position at every level (fpm.fem.tet10.fixed_nodes): the region the
        # spec's selectors name, which each finer mesh resolves better. (Holding only what the
        # mesh as given held would keep the region fixed, but a coarse mesh misses most of a
        # selector's box.)
        def solve() -> FemResult:
            solved = tet10_reference(problem, x, t, method, loads=loads, nested=nested)
            return replace(solved, loads="spread")

        mesh = TetMesh(x, t)  # a 10-node mesh's nodes: corners plus distinct edges
        return Mesh(
            refinements,
            len(x) + len(mesh.edges[0]),
            solve,
            lambda: level(refinements + 1, *mesh.refine()[:2]),
        )

    x0, t0 = np.asarray(nodes, dtype=float), np.asarray(tets, dtype=np.int64)
    first = level(0, x0, t0)
    if refine == "check":
        base = tet10_reference(problem, x0, t0, method)
        return checked(base, first.fem_nodes, first.finer, budget, None)
    levels, notes = converge(first, refine, budget, progress=progress)
    return summarise(levels, notes)


# ------------------------------------------------------------------ hexahedra


def _hex_level(
    problem: Problem,
    refinements: int,
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    fixed: np.ndarray,
    forces: np.ndarray,
    surface: np.ndarray,
    method: str,
) -> Mesh:
    """A hexahedral reference ``refinements`` times refined: the lattice's nodes are its nodes
    0 .. N - 1. Its solve is the linear 8-node reference, the lattice's forces spread
    (:func:`hexahedron_loads`), read at the lattice."""

    def solve() -> FemResult:
        f = hexahedron_loads(problem, nodes, hexahedra, forces, surface)
        gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
        if np.any(gravity):
            density = hexahedron_densities(problem, nodes, hexahedra)
            f = f + body_forces(nodes, hexahedra, density, gravity)[None]
        in_solid = np.zeros(len(nodes), dtype=bool)
        in_solid[hexahedra] = True
        free = np.repeat(in_solid & ~fixed, 3)
        how = choose_method(int(free.sum())) if method == "auto" else method
        k = hexahedron_stiffness(problem, nodes, hexahedra)  # regions: fpm.fem.materials
        u, residuals = solve_dirichlet(k, f.reshape(len(f), -1), free, nodes, how)
        u = u.reshape(len(f), -1, 3)[:, : problem.n_nodes]
        names = [case.name for case in problem.all_cases]
        return FemResult(problem.nodes.copy(), u, residuals.tolist(), names, how, loads="spread")

    def finer() -> Mesh:
        x, hx, held = refine_hexahedra(nodes, hexahedra, fixed)
        return _hex_level(problem, refinements + 1, x, hx, held, forces, surface, method)

    return Mesh(refinements, len(nodes), solve, finer)


def hexahedron_loads(
    problem: Problem,
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    forces: np.ndarray,
    surface: np.ndarray,
) -> np.ndarray:
    """(L, M, 3) nodal loads, N, on a (refined) hexahedral mesh whose first N nodes are the
    lattice's: the lattice's ``forces`` (L, N, 3) spread (:mod:`fpm.fem.loads`; ``surface`` the
    lattice's surface nodes)."""
    n = problem.n_nodes
    lattice = problem.nodes
    lattice_hexahedra = problem.solid.elements()
    assert lattice_hexahedra is not None
    spacing = lattice_spacing(lattice, lattice_hexahedra)
    h = float(spacing.max())  # the samples reach the hats and lie h / 8 apart
    loaded = lattice[np.any(forces != 0, axis=(0, 2))]
    owner, corner = np.nonzero(hexahedra < n)
    node = hexahedra[owner, corner]
    first = np.unique(node, return_index=True)[1]
    at_element = np.zeros(n, dtype=np.int64)
    at_local = np.zeros((n, 3))
    at_element[node[first]] = owner[first]
    at_local[node[first]] = NATURAL[corner[first]]
    spreaded = spread(
        lattice,
        surface,
        spacing,
        forces,
        hexahedron_surface_samples(nodes, hexahedra, loaded, h),
        lambda: hexahedron_volume_samples(nodes, hexahedra, loaded, h),
        Samples(lattice, np.ones(n), at_element, at_local),
    )
    return hexahedron_nodal_loads(hexahedra, len(nodes), spreaded.samples, spreaded.forces)


def refined_hex_reference(
    problem: Problem,
    hexahedra: np.ndarray,
    method: str,
    base: FemResult | None,
    progress: Progress | None = None,
) -> FemResult:
    """The 8-node reference refined as ``reference.refine`` says (module docstring): ``base``
    is the reference as given (point loads), which ``"check"`` returns with its estimate.
    ``progress``: as :func:`converge`'s."""
    refine = resolved_refine(problem.spec)
    budget = problem.spec.reference.node_budget or DEFAULT_NODE_BUDGET
    if problem.spec.material.model != "linear":
        raise FemError("reference.refine applies to the linear reference only")
    forces = np.stack([case.as_given().dense(problem.n_nodes) for case in problem.all_cases])
    surface = lattice_surface(hexahedra, problem.n_nodes)
    first = _hex_level(
        problem, 0, problem.nodes, hexahedra, problem.fixed.copy(), forces, surface, method
    )
    if refine == "check":
        if base is None:
            raise ValueError("the check needs the reference as given")
        limit = None if problem.spec.reference.refine == "check" else CHECK_NODES
        return checked(base, problem.n_nodes, first.finer, budget, limit)
    levels, notes = converge(first, refine, budget, progress=progress)
    return summarise(levels, notes)
