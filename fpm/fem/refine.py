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
  their numbers in a refined voxel mesh. Volume is conserved exactly, and every child is
  positive (tests/test_refine.py).
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
- **Levels** (:func:`converge`). ``refine: n`` solves levels n - 1 and n (each one refinement
  finer) and hands back level n with the change between them; ``refine: "auto"`` (the default
  for a tetrahedral mesh) solves levels 0, 1, 2, ... until the change is below
  :data:`TOLERANCE` (1%) in every load case or the next level would have more FEM nodes than
  ``reference.node_budget`` (:data:`DEFAULT_NODE_BUDGET`), or would cost as much as that many
  nodes of a well-shaped mesh (its nodes times the CG iterations the level before needed,
  over :data:`WORK_ITERATIONS`), and hands back the last level with its last change.
  ``refine: "check"`` (the default for hexahedra) keeps the 8-node reference
  on the voxels as it is, nodal point loads and all (bit for bit), and estimates its error by
  one refinement with the spread loads: the change between the two is how far the reference
  fitted against is from a solid that resolves its loads; a press on a single voxel shows here
  as a large change. The check runs on lattices whose refined mesh has at most
  :data:`CHECK_NODES` nodes unless ``refine`` names it. ``refine: 0`` is the reference as it was:
  the mesh as given, point loads, no estimate (the paper's examples name it).
- **Reported**: :attr:`FemResult.estimated_error` per load case (then validation case), the
  refinements used, each level's FEM nodes, change and seconds (:attr:`FemResult.levels`) and
  notes (a level the budget refused); a calibration warns above :data:`WARN_ERROR` (5%).

Units: m, N, Pa; changes in %.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..model.hexahedron import NATURAL
from ..model.problem import Problem, resolved_refine
from ..model.tetrahedra import EDGES, Location, boundary_faces
from .assembly import body_forces, stiffness_matrix
from .elasticity import constitutive_matrix
from .linear_solver import choose_method
from .loads import (
    Samples,
    hexahedron_nodal_loads,
    hexahedron_surface_samples,
    hexahedron_volume_samples,
    lattice_spacing,
    lattice_surface,
    spread,
    tetrahedron_nodal_loads,
    tetrahedron_surface_samples,
    tetrahedron_volume_samples,
)
from .materials import has_materials, hexahedron_densities, hexahedron_stiffness
from .solution import FemError, FemResult, solve_dirichlet
from .tet10 import Tet10Mesh, tet10_reference

TOLERANCE = 1.0
"""``refine: "auto"`` stops when the change between two levels is below this, %, in every case."""
WARN_ERROR = 5.0
"""A calibration warns about a load case whose reference's estimated error is above this, %."""
DEFAULT_NODE_BUDGET = 400_000
"""``reference.node_budget`` when not given: a refined level has at most this many FEM nodes."""
WORK_ITERATIONS = 100
"""``refine: "auto"`` also stops before a level whose predicted work, its FEM nodes times the
CG iterations per case the level before needed (refinement does not lower them), is over
``reference.node_budget`` times this: about what a well-shaped mesh needs, where one of
slivers needs many times as many (examples/lobe.vtu: 717 at the mesh as given, the cap of
1,000 once refined, 85,000 nodes taking longer than 340,000 of a well-shaped organ)."""
CHECK_NODES = 60_000
"""The default check of a hexahedral reference (``refine`` not given) runs when its refined mesh
has at most this many nodes (a lattice of about 7,500 nodes: a second or two); name
``refine: "check"`` to check a larger one (up to the node budget)."""

__all__ = [
    "CHECK_NODES",
    "DEFAULT_NODE_BUDGET",
    "TOLERANCE",
    "WARN_ERROR",
    "WORK_ITERATIONS",
    "converge",
    "refine_hexahedra",
    "refine_tetrahedra",
    "relative_change",
]


# ------------------------------------------------------------------ refinement

_OCTAHEDRON = {
    # diagonal (as mid-edge slots 0-5 of EDGES: 01, 12, 02, 03, 13, 23) -> its ring of 4
    (0, 5): (2, 3, 4, 1),
    (2, 4): (0, 3, 5, 1),
    (3, 1): (0, 2, 5, 4),
}


def refine_tetrahedra(
    nodes: np.ndarray, tets: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One uniform 1-to-8 refinement of ``tets`` (T, 4) on ``nodes`` (N, 3), m.

    Returns (N + E, 3) nodes (the old ones first, then one per distinct edge at its middle),
    (8T, 4) tetrahedra, children of tetrahedron t at 8t .. 8t + 7, all of positive volume, and
    (N + E,) bool held nodes: a new node is held when both ends of its edge are (``fixed``
    (N,), none when None), so the refined mesh holds exactly the region the coarse one held.
    """
    nodes = np.asarray(nodes, dtype=float)
    tets = np.asarray(tets, dtype=np.int64)
    n = len(nodes)
    ends = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    keys, edge = np.unique(ends[:, 0] * n + ends[:, 1], return_inverse=True)
    mid = (nodes[keys // n] + nodes[keys % n]) / 2
    all_nodes = np.concatenate([nodes, mid])
    held = np.zeros(n, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    held = np.concatenate([held, held[keys // n] & held[keys % n]])
    m = n + edge.reshape(-1, 6)  # (T, 6) mid-edge nodes, EDGES order
    x = tets
    corners = [
        (x[:, 0], m[:, 0], m[:, 2], m[:, 3]),
        (m[:, 0], x[:, 1], m[:, 1], m[:, 4]),
        (m[:, 2], m[:, 1], x[:, 2], m[:, 5]),
        (m[:, 3], m[:, 4], m[:, 5], x[:, 3]),
    ]
    # The inner octahedron along its shortest diagonal (the best shaped children).
    lengths = np.stack(
        [np.linalg.norm(all_nodes[m[:, a]] - all_nodes[m[:, b]], axis=1) for a, b in _OCTAHEDRON],
        axis=1,
    )
    choice = np.argmin(lengths, axis=1)
    inner = np.zeros((len(tets), 4, 4), dtype=np.int64)
    for option, ((a, b), ring) in enumerate(_OCTAHEDRON.items()):
        rows = choice == option
        for k in range(4):
            inner[rows, k] = np.stack(
                [m[rows, a], m[rows, b], m[rows, ring[k]], m[rows, ring[(k + 1) % 4]]], axis=1
            )
    children = np.concatenate(
        [np.stack([np.stack(c, axis=1) for c in corners], axis=1), inner], axis=1
    ).reshape(-1, 4)
    coords = all_nodes[children]
    volume = np.linalg.det(np.transpose(coords[:, 1:] - coords[:, :1], (0, 2, 1)))
    flip = volume < 0
    children[flip] = children[flip][:, [0, 2, 1, 3]]
    return all_nodes, children, held


_LOCAL = np.array([(i, j, k) for k in (-1, 0, 1) for j in (-1, 0, 1) for i in (-1, 0, 1)])
"""(27, 3) natural coordinates of a hexahedron's nodes after a split: r fastest, then s, t."""
_CORNER = ((NATURAL + 1) // 2).astype(int)  # (8, 3) each corner's 0/1 offsets
_CHILDREN = np.array(
    [
        [(a + i) + 3 * (b + j) + 9 * (c + k) for i, j, k in _CORNER]
        for c in (0, 1)
        for b in (0, 1)
        for a in (0, 1)
    ]
)
"""(8, 8) the 27-point slots of each child's corners (:mod:`fpm.model.hexahedron` order)."""


def refine_hexahedra(
    nodes: np.ndarray, hexahedra: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One uniform 1-to-8 refinement of ``hexahedra`` (H, 8) on ``nodes`` (N, 3), m, by each
    hexahedron's trilinear map.

    Returns (M, 3) nodes (the old N first; then edge middles, face centres, hexahedron
    centres, shared by neighbours), (8H, 8) hexahedra (children of h at 8h .. 8h + 7) and (M,)
    bool fixed nodes: a new node is fixed when every corner spanning it is (``fixed`` (N,), none
    when None), so a held face stays held.
    """
    nodes = np.asarray(nodes, dtype=float)
    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    held = np.zeros(len(nodes), dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    n = len(nodes)
    slots = np.empty((len(hexahedra), 27), dtype=np.int64)
    new_nodes, new_fixed = [nodes], [held]
    count = n
    for size in (1, 2, 4, 8):
        spans = [
            (a, np.flatnonzero(np.all((NATURAL == p) | (p == 0), axis=1)))
            for a, p in enumerate(_LOCAL)
        ]
        spans = [(a, s) for a, s in spans if len(s) == size]
        if size == 1:
            for a, s in spans:
                slots[:, a] = hexahedra[:, s[0]]
            continue
        ids = np.stack([hexahedra[:, s] for _, s in spans], axis=1)  # (H, K, size)
        flat = np.sort(ids.reshape(-1, size), axis=1)
        unique, inverse = np.unique(flat, axis=0, return_inverse=True)
        inverse = inverse.ravel().reshape(len(hexahedra), len(spans))
        for k, (a, _) in enumerate(spans):
            slots[:, a] = count + inverse[:, k]
        new_nodes.append(nodes[unique].mean(axis=1))
        new_fixed.append(held[unique].all(axis=1))
        count += len(unique)
    children = slots[:, _CHILDREN].reshape(-1, 8)
    return np.concatenate(new_nodes), children, np.concatenate(new_fixed)


# ------------------------------------------------------------------ levels


def relative_change(coarse: np.ndarray, fine: np.ndarray) -> list[float]:
    """Per load case, ``100 sum_i |u_fine - u_coarse| / sum_i |u_fine|`` over the nodes, %
    (``coarse``, ``fine``: (L, N, 3) displacements at the lattice nodes, m)."""
    diff = np.linalg.norm(fine - coarse, axis=2).sum(axis=1)
    scale = np.linalg.norm(fine, axis=2).sum(axis=1)
    return [float(100 * d / s) if s > 0 else 0.0 for d, s in zip(diff, scale, strict=True)]


Progress = Callable[[dict[str, Any]], None]
"""Told each level of a refined reference as it starts (:func:`converge`)."""


@dataclass
class Level:
    """One solve of the reference.

    Attributes:
        refinements: uniform refinements of the given mesh (0: as given).
        fem_nodes: the FEM's nodes at this level.
        result: its :class:`FemResult` on the lattice.
        seconds: wall time of this level (mesh, loads, assembly and solve), s.
    """

    refinements: int
    fem_nodes: int
    result: FemResult
    seconds: float


@dataclass
class Mesh:
    """A level's mesh before it is solved: its FEM node count and how to solve it."""

    refinements: int
    fem_nodes: int
    solve: Callable[[], FemResult]
    finer: Callable[[], Mesh]


def converge(
    first: Mesh,
    refine: int | str,
    budget: int,
    *,
    tolerance: float = TOLERANCE,
    progress: Progress | None = None,
) -> tuple[list[Level], list[str]]:
    """Solve the levels ``refine`` asks for, starting from the mesh ``first`` (level 0).

    ``refine`` n >= 1: levels n - 1 and n; ``"auto"``: 0, 1, ... until the change is below
    ``tolerance`` (%) in every case or the next level has more than ``budget`` FEM nodes or
    more predicted work than ``budget`` times :data:`WORK_ITERATIONS` (its FEM nodes times
    the most CG iterations a case of the level before needed).
    ``progress`` is told each level as it starts: ``{"level": refinements, "fem_nodes": n,
    "last_change": the largest change so far (%, None before two levels)}``.
    Returns the levels solved and notes (a level refused by the budget).
    """
    notes: list[str] = []
    mesh = first
    if isinstance(refine, int):
        for _ in range(max(0, refine - 1)):
            mesh = mesh.finer()
            _within(mesh, budget)  # before any solve: the spec asks for more than it allows
    levels: list[Level] = []
    last: float | None = None
    while True:
        if mesh.fem_nodes > budget and mesh.refinements > 0:  # the mesh as given always runs
            if not isinstance(refine, int) and levels:
                notes.append(
                    f"reference.refine: stopped at {levels[-1].refinements} refinement(s): the "
                    f"next would have {mesh.fem_nodes:,} FEM nodes, over reference.node_budget "
                    f"({budget:,})"
                )
                break
            _within(mesh, budget)
        iterations = max(levels[-1].result.iterations, default=0) if levels else 0
        if not isinstance(refine, int) and mesh.fem_nodes * iterations > budget * WORK_ITERATIONS:
            notes.append(
                f"reference.refine: stopped at {levels[-1].refinements} refinement(s): the next "
                f"would have {mesh.fem_nodes:,} FEM nodes, and at the {iterations:,} CG "
                f"iterations per case this level needed (a well-shaped mesh needs about "
                f"{WORK_ITERATIONS}; slivers need more) it would cost as much as "
                f"{mesh.fem_nodes * iterations // WORK_ITERATIONS:,} nodes, over "
                f"reference.node_budget ({budget:,}): improve the mesh's worst tetrahedra, or "
                "raise reference.node_budget"
            )
            break
        if progress is not None:
            progress({"level": mesh.refinements, "fem_nodes": mesh.fem_nodes, "last_change": last})
        t0 = time.perf_counter()
        result = mesh.solve()
        levels.append(Level(mesh.refinements, mesh.fem_nodes, result, time.perf_counter() - t0))
        if isinstance(refine, int):
            if mesh.refinements >= refine:
                break
        elif len(levels) >= 2:
            change = relative_change(levels[-2].result.displacements, result.displacements)
            last = max(change, default=0.0)
            if last < tolerance:
                break
        mesh = mesh.finer()
    return levels, notes


def _within(mesh: Mesh, budget: int) -> None:
    """Raise when a level the spec names has more FEM nodes than the budget."""
    if mesh.fem_nodes > budget:
        raise FemError(
            f"reference.refine: {mesh.refinements} refinement(s) make {mesh.fem_nodes:,} FEM "
            f"nodes, over reference.node_budget ({budget:,}): ask for fewer, or 'auto', or raise "
            "reference.node_budget"
        )


def summarise(levels: list[Level], notes: list[str], loads: str = "spread") -> FemResult:
    """The last level's result, with the estimated error (its change from the level before)
    and every level's figures."""
    last = levels[-1].result
    table: list[dict[str, Any]] = []
    for i, level in enumerate(levels):
        change = (
            relative_change(levels[i - 1].result.displacements, level.result.displacements)
            if i
            else None
        )
        table.append(
            {
                "refinements": level.refinements,
                "fem_nodes": level.fem_nodes,
                "change": change,
                "seconds": round(level.seconds, 3),
                "iterations": list(level.result.iterations),
            }
        )
    error = table[-1]["change"]
    if error is None:
        notes = [*notes, "reference.refine: one level only, so its error is not estimated"]
    return replace(
        last,
        estimated_error=error,
        refinements=levels[-1].refinements,
        levels=table,
        loads=loads,
        notes=list(last.notes) + notes,
    )


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
        corners = mesh.nodes[: mesh.n_corners]
        tets = mesh.corners
        loaded = lattice[np.any(forces != 0, axis=(0, 2))]
        faces, owner = boundary_faces(tets)
        at_nodes = Samples(lattice, np.ones(len(lattice)), where.element, where.lam)
        spreaded = spread(
            lattice,
            surface,
            spacing,
            forces,
            tetrahedron_surface_samples(corners, tets, faces, owner, loaded, h),
            lambda: tetrahedron_volume_samples(corners, tets, loaded, h),
            at_nodes,
        )
        return tetrahedron_nodal_loads(
            mesh.elements, len(mesh.nodes), spreaded.samples, spreaded.forces
        )

    return loads


def _tet10_nodes(nodes: np.ndarray, tets: np.ndarray) -> int:
    """Nodes of the 10-node mesh on ``tets``: corners plus distinct edges."""
    n = len(nodes)
    ends = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    return n + len(np.unique(ends[:, 0] * n + ends[:, 1]))


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

    def level(refinements: int, x: np.ndarray, t: np.ndarray) -> Mesh:
        # Supports by position at every level (fpm.fem.tet10.fixed_nodes): the region the
        # spec's selectors name, which each finer mesh resolves better. (Holding only what the
        # mesh as given held would keep the region fixed, but a coarse mesh misses most of a
        # selector's box: the 360-tetrahedron organ held below z = -25 mm moved 2.4 times as
        # much as the lattice that holds every node there.)
        def solve() -> FemResult:
            return replace(tet10_reference(problem, x, t, method, loads=loads), loads="spread")

        return Mesh(
            refinements,
            _tet10_nodes(x, t),
            solve,
            lambda: level(refinements + 1, *refine_tetrahedra(x, t)[:2]),
        )

    x0, t0 = np.asarray(nodes, dtype=float), np.asarray(tets, dtype=np.int64)
    first = level(0, x0, t0)
    if refine == "check":
        base = tet10_reference(problem, x0, t0, method)
        return _checked(base, first.fem_nodes, first.finer, budget, None)
    levels, notes = converge(first, refine, budget, progress=progress)
    return summarise(levels, notes)


def _checked(
    base: FemResult,
    base_nodes: int,
    refined: Callable[[], Mesh],
    budget: int,
    limit: int | None,
) -> FemResult:
    """``base`` (the reference as given, ``base_nodes`` FEM nodes) with its error estimated
    against one refinement with spread loads (``refined``), unless that has more FEM nodes than
    ``budget`` (or ``limit``)."""
    cap = budget if limit is None else min(budget, limit)
    finer = refined() if 4 * base_nodes <= cap else None  # a refined mesh has ~8x the nodes
    if finer is None or finer.fem_nodes > cap:
        if limit is not None:  # the default check, on a lattice too large for it: no estimate
            return base
        size = f"{finer.fem_nodes:,}" if finer is not None else f"about {8 * base_nodes:,}"
        why = (
            f"reference.refine 'check': not run, its refined mesh would have {size} FEM nodes, "
            f"over reference.node_budget ({cap:,}); the reference's error is not estimated"
        )
        return replace(base, notes=[*base.notes, why])
    t0 = time.perf_counter()
    check = finer.solve()
    seconds = time.perf_counter() - t0
    error = relative_change(base.displacements, check.displacements)
    table: list[dict[str, Any]] = [
        {"refinements": 0, "fem_nodes": base_nodes, "change": None, "loads": "nodal"},
        {
            "refinements": 1,
            "fem_nodes": finer.fem_nodes,
            "change": error,
            "seconds": round(seconds, 3),
            "loads": "spread",
        },
    ]
    return replace(base, estimated_error=error, refinements=0, levels=table)


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
    0 .. N - 1."""

    def solve() -> FemResult:
        return _solve_hex(problem, nodes, hexahedra, fixed, forces, surface, method)

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


def _solve_hex(
    problem: Problem,
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    fixed: np.ndarray,
    forces: np.ndarray,
    surface: np.ndarray,
    method: str,
) -> FemResult:
    """The linear 8-node reference on a (refined) hexahedral mesh whose first N nodes are the
    lattice's, the lattice's forces spread (:func:`hexahedron_loads`), read at the lattice."""
    n = problem.n_nodes
    lattice = problem.nodes
    f = hexahedron_loads(problem, nodes, hexahedra, forces, surface)
    material = problem.spec.material
    gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
    if np.any(gravity):
        density = (
            hexahedron_densities(problem, nodes, hexahedra)
            if has_materials(problem.spec)
            else material.density
        )
        f = f + body_forces(nodes, hexahedra, density, gravity)[None]
    in_solid = np.zeros(len(nodes), dtype=bool)
    in_solid[hexahedra] = True
    free = np.repeat(in_solid & ~fixed, 3)
    how = choose_method(int(free.sum())) if method == "auto" else method
    if has_materials(problem.spec):  # regions, transversely isotropic: fpm.fem.materials
        k = hexahedron_stiffness(problem, nodes, hexahedra)
    else:
        k = stiffness_matrix(
            nodes,
            hexahedra,
            constitutive_matrix(material.youngs_modulus, material.poisson_ratio),
            problem.spec.reference.integration,
        )
    u, residuals = solve_dirichlet(k, f.reshape(len(f), -1), free, nodes, how)
    u = u.reshape(len(f), -1, 3)[:, :n]
    names = [case.name for case in problem.all_cases]
    return FemResult(lattice.copy(), u, residuals.tolist(), names, how, loads="spread")


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
        return _checked(base, problem.n_nodes, first.finer, budget, limit)
    levels, notes = converge(first, refine, budget, progress=progress)
    return summarise(levels, notes)
