"""The 10-node tetrahedron: a linear-elastic FEM reference on the user's own tetrahedral mesh.

A voxel lattice made from a tetrahedral mesh (:mod:`fpm.io.meshes`) is a staircase of the organ;
solved with hexahedra it misses the organ's own displacements by 7-17%. This module solves the
reference on the tetrahedra themselves, with quadratic (10-node) tetrahedra, and reads the
answer at the lattice's nodes, which is what the fit compares.

- **Element.** Every 4-node tetrahedron gets a node at the middle of each of its 6 edges (an
  edge shared by several tetrahedra gets one node), local order as VTK's ``tetra10``: corners
  0-3, then edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3). Edges are straight, so the map from
  barycentric coordinates ``L`` is affine and the shape functions are
  ``N_i = L_i (2 L_i - 1)`` at corners and ``N_ij = 4 L_i L_j`` at mid-edges, with constant
  ``grad L`` per element. The stiffness ``int B^T C B dV`` has a quadratic integrand, which the
  4-point Gauss rule (degree 2) integrates exactly. Body force: ``int N_a rho g dV`` (exact:
  ``-V/20`` per corner and ``V/5`` per mid-edge node, times ``rho g``).
- **Assembly.** Element matrices are computed vectorised over chunks of elements and summed into
  3x3 node blocks (BSR), the unknowns node-major, so :func:`fpm.fem.solution.solve_dirichlet`
  solves it as it solves the hexahedra (sparse LU when small, AMG-preconditioned CG above).
- **Reading at points** (:meth:`~fpm.model.tetrahedra.TetMesh.locate`: with the mesh's checks,
  so that the service finds where points lie without the solvers). Each point is found in a
  tetrahedron by its barycentric coordinates (all >= -1e-9), candidates the tetrahedra whose
  centroids are nearest and then, where those miss, every tetrahedron whose centroid lies within
  the largest circumscribing distance (so none is missed). A point in no tetrahedron takes the
  nearest point of the mesh's boundary triangles (exact: candidates within the first estimate
  plus the largest triangle's reach), and its tetrahedron. Values there are the quadratic
  interpolation (:func:`interpolate`).
- **Point loads** (:func:`point_loads`): a force at a point goes to the nodes of the tetrahedron
  holding it, in proportion to their shape function values there (the consistent point load:
  the work ``f . u(x)`` is the same for every quadratic field).

Units: m, N, Pa, kg/m^3. Shapes are given per function.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import scipy.sparse as sp
from pyamg.util.utils import get_block_diag
from scipy.spatial import cKDTree

from ..model.problem import Problem
from ..model.tetrahedra import (
    EDGES,
    Location,
    TetMesh,
    TetMeshError,
    barycentric,
    edge_matrices,
    signed_volumes,
    validate_tetrahedra,
)
from . import linear_solver
from .assembly import keep_nodes, unique_inverse
from .elasticity import constitutive_matrix, strain_displacement
from .linear_solver import (
    AMG_MAX_ITERATIONS,
    NegativeCurvature,
    amg_hierarchy,
    choose_method,
    rigid_body_modes,
    v_cycle,
)
from .load_case_cg import compiled_sweep_columns, solve_columns
from .materials import has_materials, tetrahedron_elasticity
from .solution import FemError, FemResult
from .solution import solve_dirichlet as _solve_direct

_A, _B = 0.5854101966249685, 0.1381966011250105
GAUSS_4 = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])
"""(4, 4) barycentric coordinates of the 4-point Gauss rule (degree 2); each weight is V / 4."""

CG_TOLERANCE = 1e-5
"""The p-multigrid CG's relative residual ||K u - f|| / ||f||. The reference is judged to
0.1-1% (its estimated error, the change from one level to the next); the CG's own error at
the lattice nodes stays orders of magnitude below that."""
RESIDUAL_LIMIT = 10 * CG_TOLERANCE
"""A relative residual above this after the solve means K was (nearly) singular."""
CHUNK = 4096
"""Elements per chunk of the stiffness assembly (bounds the (chunk, 30, 30) temporaries)."""


@dataclass(frozen=True)
class Tet10Mesh:
    """10-node tetrahedra on a 4-node mesh.

    Attributes:
        nodes: (M, 3) node positions, m: the 4-node mesh's nodes first, in their order, then one
            node per distinct edge at its middle.
        elements: (T, 10) node indices, local order of :data:`EDGES` (VTK ``tetra10``).
        n_corners: N, the 4-node mesh's node count.
    """

    nodes: np.ndarray
    elements: np.ndarray
    n_corners: int

    @property
    def corners(self) -> np.ndarray:
        """(T, 4) the 4-node tetrahedra."""
        return self.elements[:, :4]


def quadratic_mesh(nodes: np.ndarray, tets: np.ndarray) -> Tet10Mesh:
    """The :class:`Tet10Mesh` of ``tets`` (T, 4) on ``nodes`` (N, 3), m (checked by
    :func:`validate_tetrahedra`). Shared edges share their mid-edge node."""
    mesh = TetMesh(nodes, tets)
    validate_tetrahedra(mesh.nodes, mesh.tets)
    n = len(mesh.nodes)
    elements = np.concatenate([mesh.tets, n + mesh.edges[1]], axis=1)
    return Tet10Mesh(np.concatenate([mesh.nodes, mesh.midpoints]), elements, n)


def barycentric_gradients(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """grad L_k (T, 4, 3), 1/m, and volumes (T,), m^3, of tetrahedra with corners ``coords``
    (T, 4, 3), m."""
    inverse = np.linalg.inv(edge_matrices(coords))  # rows: grad L_1, grad L_2, grad L_3
    grads = np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)
    return grads, signed_volumes(coords)


def shape_functions(lam: np.ndarray) -> np.ndarray:
    """(..., 10) quadratic shape functions at barycentric coordinates ``lam`` (..., 4)."""
    corner = lam * (2 * lam - 1)
    edge = 4 * lam[..., EDGES[:, 0]] * lam[..., EDGES[:, 1]]
    return np.concatenate([corner, edge], axis=-1)


def shape_gradients(lam: np.ndarray, grads: np.ndarray) -> np.ndarray:
    """(T, 10, 3) dN_a/dx, 1/m, at barycentric point ``lam`` (4,) of tetrahedra whose
    barycentric gradients are ``grads`` (T, 4, 3)."""
    corner = (4 * lam - 1)[None, :, None] * grads
    i, j = EDGES[:, 0], EDGES[:, 1]
    edge = 4 * (lam[i][None, :, None] * grads[:, j] + lam[j][None, :, None] * grads[:, i])
    return np.concatenate([corner, edge], axis=1)


def element_stiffness(coords: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(T, 30, 30) element stiffness, N/m, of straight-edged 10-node tetrahedra with corners
    ``coords`` (T, 4, 3), m, and elasticity ``c`` (6, 6), Pa (4-point Gauss rule: exact)."""
    grads, volume = barycentric_gradients(coords)
    ke = np.zeros((len(coords), 30, 30))
    for lam in GAUSS_4:
        b = strain_displacement(shape_gradients(lam, grads))
        ke += np.matmul(np.transpose(b, (0, 2, 1)), np.matmul(c, b)) * (volume / 4)[:, None, None]
    return ke


def stiffness_matrix(mesh: Tet10Mesh, c: np.ndarray) -> sp.bsr_matrix:
    """(3M, 3M) global stiffness K, N/m, in 3x3 node blocks, unknowns node-major.

    Args:
        mesh: the 10-node mesh (M nodes).
        c: (6, 6) elasticity matrix, Pa (:func:`fpm.fem.elasticity.constitutive_matrix`), or
            (T, 6, 6) one per tetrahedron (:mod:`fpm.fem.materials`).
    """
    m = len(mesh.nodes)
    elements = mesh.elements.astype(np.int64)
    keys = (np.repeat(elements, 10, axis=1) * m + np.tile(elements, (1, 10))).ravel()
    pairs, slot = unique_inverse(keys)
    del keys
    data = np.zeros((len(pairs), 9))
    coords = mesh.nodes[mesh.corners]
    add = _compiled_add_blocks()
    for start in range(0, len(elements), CHUNK):
        stop = min(start + CHUNK, len(elements))
        ke = element_stiffness(coords[start:stop], c if c.ndim == 2 else c[start:stop])
        add(data, slot[start * 100 : stop * 100], ke)
    indptr = np.searchsorted(pairs // m, np.arange(m + 1))
    return sp.bsr_matrix((data.reshape(-1, 3, 3), pairs % m, indptr), shape=(3 * m, 3 * m))


def _add_blocks(data: np.ndarray, where: np.ndarray, ke: np.ndarray) -> None:
    """``data`` (P, 9) += the 3x3 node blocks of element matrices ``ke`` (E, 30, 30), block
    (a, b) of element e into row ``where[100 e + 10 a + b]`` (row-major 3x3). In element order,
    as one sum per global block."""
    for e in range(ke.shape[0]):
        for a in range(10):
            for b in range(10):
                s = where[100 * e + 10 * a + b]
                for i in range(3):
                    for j in range(3):
                        data[s, 3 * i + j] += ke[e, 3 * a + i, 3 * b + j]


@cache
def _compiled_add_blocks() -> Callable[[np.ndarray, np.ndarray, np.ndarray], None]:
    """:func:`_add_blocks` compiled by numba on first use (as the FEM's compiled smoother)."""
    from numba import njit

    return njit(cache=True, nogil=True)(_add_blocks)


def body_forces(mesh: Tet10Mesh, density: float | np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """(M, 3) consistent nodal body forces ``int N_a rho g dV``, N: each tetrahedron of volume
    V gives ``-V/20`` to its corners and ``V/5`` to its mid-edge nodes, times ``rho g``
    (``density`` kg/m^3, or (T,) one per tetrahedron; ``gravity`` (3,) m/s^2); they sum to the
    weight ``rho g V``."""
    volume = signed_volumes(mesh.nodes[mesh.corners])
    if np.ndim(density):  # per tetrahedron
        volume = volume * np.asarray(density, dtype=float)
        density = 1.0
    share = np.concatenate(
        [np.repeat(-volume[:, None] / 20, 4, axis=1), np.repeat(volume[:, None] / 5, 6, axis=1)],
        axis=1,
    )
    total = np.bincount(mesh.elements.ravel(), share.ravel(), len(mesh.nodes))
    return total[:, None] * (density * np.asarray(gravity, dtype=float))[None, :]


def interpolate(mesh: Tet10Mesh, values: np.ndarray, where: Location) -> np.ndarray:
    """(..., P, 3) nodal ``values`` (..., M, 3) interpolated at located points."""
    weights = shape_functions(where.lam)  # (P, 10)
    return np.einsum("...pac,pa->...pc", values[..., mesh.elements[where.element], :], weights)


@dataclass
class NestedStart:
    """Nested iteration over a refined reference's levels: each level's CG starts from the field
    of the level before, its quadratic interpolation at the finer mesh's nodes, rather than from
    zero. The 1-to-8 split (:meth:`fpm.model.tetrahedra.TetMesh.refine`) keeps every child in
    its parent (children of tetrahedron t at 8t .. 8t + 7), so each node's parent is known and
    the start is exact where the coarse field is right; only the part of the answer the coarse
    mesh could not hold is left for the iterations.

    Attributes:
        mesh: the last level solved (None before the first).
        u: (L, M, 3) its displacements at every node, m.
    """

    mesh: Tet10Mesh | None = None
    u: np.ndarray | None = None

    def keep(self, mesh: Tet10Mesh, u: np.ndarray) -> None:
        """Remember ``mesh``'s displacements ``u`` (L, M, 3), m, for the next level."""
        self.mesh, self.u = mesh, u

    def guess(self, mesh: Tet10Mesh) -> np.ndarray | None:
        """(L, M', 3) the kept field at the nodes of ``mesh`` when it is the kept mesh's 1-to-8
        split (8 children per tetrahedron), m; else None (nothing to start from)."""
        coarse, u = self.mesh, self.u
        if coarse is None or u is None or len(mesh.elements) != 8 * len(coarse.elements):
            return None
        node, first = np.unique(mesh.elements.ravel(), return_index=True)
        parent = first // mesh.elements.shape[1] // 8
        lam = barycentric(coarse.nodes[coarse.corners[parent]], mesh.nodes[node])
        weights = shape_functions(lam)  # (M', 10)
        start = np.zeros((len(u), len(mesh.nodes), 3))
        for case in range(len(u)):  # one case at a time: (M', 10, 3) at once, not (L, M', 10, 3)
            values = u[case][coarse.elements[parent]]
            start[case, node] = np.einsum("mac,ma->mc", values, weights)
        return start


def point_loads(mesh: Tet10Mesh, forces: np.ndarray, where: Location) -> np.ndarray:
    """(..., M, 3) nodal forces, N, equivalent to point ``forces`` (..., P, 3), N, at located
    points: each goes to its tetrahedron's 10 nodes times their shape function values there."""
    weights = shape_functions(where.lam)  # (P, 10)
    shares = forces[..., :, None, :] * weights[:, :, None]  # (..., P, 10, 3)
    nodes = mesh.elements[where.element].ravel()
    flat = shares.reshape(*forces.shape[:-2], -1, 3)
    out = np.zeros((*forces.shape[:-2], len(mesh.nodes), 3))
    for i in range(3):
        out[..., i] = np.apply_along_axis(
            lambda s: np.bincount(nodes, s, len(mesh.nodes)), -1, flat[..., i]
        )
    return out


# ------------------------------------------------------------------ the reference at the lattice


def fixed_nodes(problem: Problem, mesh: Tet10Mesh) -> np.ndarray:
    """(M,) bool: the 10-node mesh's nodes held by the spec's ``fixed`` selectors.

    Each selector is applied by position, h the lattice spacing (:attr:`Problem.h`):

    - ``face``: the nodes less than h/2 from the lattice's face plane or beyond it (the
      lattice's face stands for the solid up to its first cell centres);
    - ``box``: the nodes inside the box (widened by 1e-3 h); if none is, as below for each
      lattice node in it;
    - ``node``, ``at``, ``nearest``: the nodes within h/2 of the lattice node it names, or the
      nearest node when none is that close.
    """
    from ..model.problem import select_nodes

    x = mesh.nodes
    h = problem.h
    lo, hi = problem.nodes.min(axis=0), problem.nodes.max(axis=0)
    fixed = np.zeros(len(x), dtype=bool)
    tree: cKDTree | None = None
    for sel in problem.spec.fixed:
        if sel.face is not None:
            axis = "xyz".index(sel.face[0])
            if sel.face[1] == "-":
                fixed |= x[:, axis] < lo[axis] + h / 2 * (1 - 1e-6)
            else:
                fixed |= x[:, axis] > hi[axis] - h / 2 * (1 - 1e-6)
            continue
        if sel.box is not None:
            box_lo = np.asarray(sel.box[0]) - 1e-3 * h
            box_hi = np.asarray(sel.box[1]) + 1e-3 * h
            inside = np.all((x >= box_lo) & (x <= box_hi), axis=1)
            if inside.any():
                fixed |= inside
                continue
        tree = tree or cKDTree(x)
        for point in problem.nodes[select_nodes(problem, sel)]:
            close = tree.query_ball_point(point, h / 2)
            fixed[close if close else [tree.query(point)[1]]] = True
    return fixed


def tet10_reference(
    problem: Problem,
    nodes: np.ndarray,
    tets: np.ndarray,
    method: str = "auto",
    *,
    loads: Callable[[Tet10Mesh, Location], np.ndarray] | None = None,
    nested: NestedStart | None = None,
) -> FemResult:
    """The linear-elastic reference of ``problem`` solved with 10-node tetrahedra on the mesh
    ``tets`` (T, 4) on ``nodes`` (N, 3), m, read at the lattice's nodes.

    The load cases' nodal forces (then the validation cases') are applied at the lattice node's
    position in the mesh (:func:`point_loads`), with ``fpm.gravity`` the mesh's consistent
    weight; supports by :func:`fixed_nodes`. The displacements are read at every lattice node
    (:meth:`~fpm.model.tetrahedra.TetMesh.locate`, :func:`interpolate`); a lattice node the
    spec fixes reads 0 (it is held in the fit's model too). ``loads`` (mesh, where the lattice
    nodes lie) -> (L, M, 3) nodal forces replaces the point loads (:mod:`fpm.fem.refine`
    spreads them: :mod:`fpm.fem.loads`). ``nested``: the CG starts from the level before's
    field where this mesh is its split, and the field is kept for the next
    (:class:`NestedStart`; the direct solve takes no start).

    Returns:
        a :class:`FemResult` on the lattice: displacements (L, N_lattice, 3), m; ``element``
        ``"tet10"``.

    Raises:
        FemError: a bad mesh (the element named), a neo-Hookean material, or a mesh the fixed
            nodes do not hold.
    """
    material = problem.spec.material
    if material.model != "linear":
        raise FemError(
            "the tetrahedral reference (reference.mesh) is linear: use material.model "
            "'linear', or drop reference.mesh for the neo-Hookean voxel reference"
        )
    if method not in ("auto", "direct", "amg"):
        raise ValueError(f"unknown method {method!r} (use 'auto', 'direct' or 'amg')")
    try:
        mesh = quadratic_mesh(nodes, tets)
    except TetMeshError as e:
        raise FemError(f"reference.mesh: {e}") from None
    lattice = problem.nodes
    where = TetMesh(mesh.nodes[: mesh.n_corners], mesh.corners).locate(lattice)
    cases = problem.all_cases
    lattice_forces = np.stack([case.as_given().dense(len(lattice)) for case in cases])  # (L, N, 3)
    if loads is None:
        forces = point_loads(mesh, lattice_forces, where)
    else:
        forces = loads(mesh, where)
    c: np.ndarray = constitutive_matrix(material.youngs_modulus, material.poisson_ratio)
    density: float | np.ndarray = material.density
    if has_materials(problem.spec):  # regions, transversely isotropic: per tetrahedron
        c, density = tetrahedron_elasticity(problem, mesh.nodes, mesh.corners)
    gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
    if np.any(gravity):
        forces = forces + body_forces(mesh, density, gravity)[None]
    fixed = fixed_nodes(problem, mesh)
    if not fixed.any():
        raise FemError(
            "the tetrahedral mesh is not held: no node of it is near the spec's fixed nodes"
        )
    used = np.zeros(len(mesh.nodes), dtype=bool)
    used[mesh.elements] = True  # a node in no tetrahedron has no stiffness: it stays at rest
    free = np.repeat(~fixed & used, 3)
    method = choose_method(int(free.sum())) if method == "auto" else method
    k = stiffness_matrix(mesh, c)
    f = forces.reshape(len(cases), -1)
    if method == "direct":
        u, residuals, iterations = solve_direct(k, f, free, mesh, method)
    else:
        start = None if nested is None else nested.guess(mesh)
        u, residuals, iterations = solve_p_multigrid(
            k, f, free, mesh, method, start=None if start is None else start.reshape(len(f), -1)
        )
    if nested is not None:
        nested.keep(mesh, u.reshape(len(cases), -1, 3))
    u_lattice = interpolate(mesh, u.reshape(len(cases), -1, 3), where)
    u_lattice[:, problem.fixed] = 0.0
    names = [case.name for case in cases]
    return FemResult(
        lattice.copy(),
        u_lattice,
        residuals.tolist(),
        names,
        method,
        element="tet10",
        iterations=iterations,
    )


def solve_direct(
    k: sp.bsr_matrix, forces: np.ndarray, free: np.ndarray, mesh: Tet10Mesh, method: str
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Sparse LU, as :func:`fpm.fem.solution.solve_dirichlet` (arguments and returns as
    :func:`solve_p_multigrid`; no iterations)."""
    u, residuals = _solve_direct(k, forces, free, mesh.nodes, method)
    return u, residuals, []


def corner_prolongation(mesh: Tet10Mesh) -> sp.csr_matrix:
    """(M, N) node values of the 10-node mesh from its N corners: the linear field, each
    mid-edge node the mean of its edge's ends."""
    m, n = len(mesh.nodes), mesh.n_corners
    edges, first = np.unique(mesh.elements[:, 4:].ravel(), return_index=True)
    ends = mesh.elements[:, EDGES].reshape(-1, 2)[first]
    rows = np.concatenate([np.arange(n), edges, edges])
    cols = np.concatenate([np.arange(n), ends[:, 0], ends[:, 1]])
    values = np.concatenate([np.ones(n), np.full(2 * len(edges), 0.5)])
    return sp.csr_matrix((values, (rows, cols)), shape=(m, n))


def solve_p_multigrid(
    k: sp.bsr_matrix,
    forces: np.ndarray,
    free: np.ndarray,
    mesh: Tet10Mesh,
    method: str = "amg",
    *,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Solve K u = f, u = 0 where not ``free``, by CG preconditioned with a two-grid p-multigrid
    cycle: a forward 3x3 block Gauss-Seidel sweep on the quadratic K, the correction on the
    linear (corner) field ``P^T K P`` by the project's smoothed-aggregation V-cycle
    (:func:`fpm.fem.linear_solver.amg_hierarchy`, rigid-body modes), a backward sweep
    (symmetric, as CG needs; against smoothed aggregation on the quadratic K itself:
    bench/bench_fem.py).

    Args:
        k: (3M, 3M) stiffness, N/m, 3x3 blocks (:func:`stiffness_matrix`).
        forces: (L, 3M) nodal forces, N.
        free: (3M,) bool, whole nodes (the three unknowns of a node together).
        mesh: the 10-node mesh.
        method: unused (the signature of :func:`solve_direct`).
        start: (L, 3M) displacements the CG starts from, m (None: from zero;
            :class:`NestedStart`).

    Returns:
        u (L, 3M), m; residuals (L,) ||K u - f|| / ||f|| over the free unknowns; the CG
        iterations per load case (a mesh of slivers needs many times those of a well-shaped
        one: :mod:`fpm.fem.refine` predicts a finer level's work from them).

    Raises:
        FemError: K restricted to the free unknowns is singular (part of the mesh not held).
    """
    nodes_free = free.reshape(-1, 3)[:, 0]
    kff = keep_nodes(k, nodes_free)
    kff.sort_indices()
    corners_free = nodes_free[: mesh.n_corners]
    pn = corner_prolongation(mesh)[nodes_free][:, corners_free]
    p = sp.kron(pn, sp.identity(3), format="csr")
    singular = FemError(
        "the stiffness matrix is singular: part of the tetrahedral mesh can still move freely "
        "(fix more nodes, or join loose tetrahedra by a face)"
    )
    kc = sp.bsr_matrix(p.T @ kff @ p, blocksize=(3, 3))
    hierarchy = amg_hierarchy(kc, rigid_body_modes(mesh.nodes[: mesh.n_corners][corners_free]))
    inverse = get_block_diag(kff, blocksize=3, inv_flag=True)
    sweep = compiled_sweep_columns()
    restrict = p.T.tocsr()

    def precondition(r: np.ndarray) -> np.ndarray:  # (n, c) -> (n, c), column by column
        x = np.zeros_like(r)
        sweep(kff.indptr, kff.indices, kff.data, inverse, x, r, True)
        coarse = restrict @ (r - kff @ x)
        corrections = [v_cycle(hierarchy, np.ascontiguousarray(col)) for col in coarse.T]
        x += p @ np.stack(corrections, axis=1)
        sweep(kff.indptr, kff.indices, kff.data, inverse, x, r, False)
        return x

    f = np.ascontiguousarray(forces[:, free].T)  # (n, L)
    u = np.zeros_like(forces, dtype=float)
    try:  # the load cases in lockstep, in up to COLUMN_THREADS groups: the same for any
        results = solve_columns(
            kff,
            f,
            precondition,
            rtol=CG_TOLERANCE,
            max_iterations=AMG_MAX_ITERATIONS,
            threads=linear_solver.COLUMN_THREADS,
            x0=None if start is None else np.ascontiguousarray(start[:, free].T),
        )
    except NegativeCurvature:
        raise singular from None
    for case, result in enumerate(results):
        u[case, free] = result.x
    residuals = np.array([r.residual for r in results])
    iterations = [int(r.iterations) for r in results]
    unmet = not all(r.converged for r in results)  # within AMG_MAX_ITERATIONS
    if unmet or not np.all(np.isfinite(u)) or residuals.max(initial=0.0) > RESIDUAL_LIMIT:
        raise singular
    return u, residuals, iterations
