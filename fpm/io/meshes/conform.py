"""The surface-conforming lattice: a voxel lattice's surface nodes moved onto the surface of
its tetrahedral mesh (m)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import MeshError
from .graded import GradedLattice, graded_lattice
from .voxelise import _fmt

KEPT_JACOBIAN = 0.1
""":func:`conform_lattice` keeps every hexahedron's smallest Jacobian determinant at least this
fraction of its voxel's."""
CROSSING_PAIRS = 2_000_000
""":func:`line_crossings` tries at most this many line-triangle pairs at once (memory)."""
RAY_REACH = 1.5
""":func:`conform_lattice` moves a surface node along its outward normal when the mesh's
surface crosses that line within this many h of it (a voxel's surface node is within
sqrt(3) h / 2 of the surface when the voxels are the cells whose centres are inside)."""


def outward_normals(hexahedra: np.ndarray, n_nodes: int) -> np.ndarray:
    """(N, 3) per lattice node the sum of the outward unit normals (lattice axes) of the
    boundary faces of ``hexahedra`` (H, 8) it is a corner of; zero off the surface."""
    from ...fem.samples import boundary_hexahedron_faces

    corners, _, local = boundary_hexahedron_faces(hexahedra)
    faces = np.zeros((len(local), 3))
    faces[np.arange(len(local)), local // 2] = np.where(local % 2 == 1, 1.0, -1.0)
    out = np.zeros((n_nodes, 3))
    np.add.at(out, corners, faces[:, None, :])
    return out


def line_crossings(
    points: np.ndarray, directions: np.ndarray, triangles: np.ndarray, reach: float = np.inf
) -> np.ndarray:
    """(P,) for each line ``points`` + t ``directions`` (P, 3; unit directions) the t, m, of
    its crossing with ``triangles`` (F, 3, 3) nearest the point (either side) within ``reach``
    (m) of it, inf where there is none (Moller-Trumbore). With a finite reach only the
    triangles whose centres lie within reach plus the largest triangle's radius are tried
    (a k-d tree), in chunks of at most CROSSING_PAIRS line-triangle pairs."""
    from scipy.spatial import cKDTree

    centre = triangles.mean(axis=1)
    radius = float(np.linalg.norm(triangles - centre[:, None], axis=2).max())
    if np.isfinite(reach):
        near = cKDTree(centre).query_ball_point(points, reach + radius)
    else:
        near = [range(len(triangles))] * len(points)
    width = max((len(n) for n in near), default=0)
    out = np.full(len(points), np.inf)
    if width == 0:
        return out
    candidates = np.full((len(points), width), -1)
    for i, n in enumerate(near):
        candidates[i, : len(n)] = list(n)
    chunk = max(1, CROSSING_PAIRS // width)
    for first in range(0, len(points), chunk):
        rows = slice(first, first + chunk)
        which = candidates[rows]
        tri = triangles[np.maximum(which, 0)]  # (C, W, 3, 3)
        a, e1, e2 = tri[:, :, 0], tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
        d = directions[rows][:, None, :]
        p = np.cross(d, e2)
        det = np.einsum("cwk,cwk->cw", e1, p)
        usable = (which >= 0) & (np.abs(det) > 1e-12 * np.einsum("cwk,cwk->cw", e1, e1))
        inverse = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)
        s = points[rows][:, None, :] - a
        u = inverse * np.einsum("cwk,cwk->cw", s, p)
        q = np.cross(s, e1)
        v = inverse * np.einsum("cwk,cwk->cw", np.broadcast_to(d, q.shape), q)
        t = inverse * np.einsum("cwk,cwk->cw", e2, q)
        eps = 1e-9
        crossed = usable & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (np.abs(t) <= reach)
        t = np.where(crossed, t, np.inf)
        out[rows] = t[np.arange(len(t)), np.argmin(np.abs(t), axis=1)]
    return out


def conform_lattice(
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    mesh_nodes: np.ndarray,
    tets: np.ndarray,
    *,
    boxes: list[tuple[np.ndarray, np.ndarray]] | None = None,
    tol: float = 0.0,
) -> np.ndarray:
    """(N, 3) a voxel lattice's ``nodes`` (N, 3), m, with its surface nodes (the corners of
    its boundary faces, ``hexahedra`` (H, 8)) moved onto the surface of the tetrahedra
    ``tets`` (T, 4) on ``mesh_nodes`` (M, 3): a surface-conforming lattice, the mesh's solid
    instead of its staircase. Each surface node goes along its outward normal (the sum of its
    boundary faces' outward normals: straight out from a flat part of the staircase,
    diagonally out from a step's edge or corner) to where that line crosses the mesh's
    surface, if it does within :data:`RAY_REACH` h, else to its nearest point of the surface
    (docs/notes/2026-11-29-organs-surface-nodes.md says why). It goes all the way unless a
    hexahedron of it would keep less than :data:`KEPT_JACOBIAN` of its voxel's smallest
    Jacobian determinant; those hexahedra's surface nodes go 0.8 of the way, then 0.8 of that,
    until none does (every hexahedron stays positive).

    The selectors stay true: a node inside one of the ``boxes`` (lo, hi) (within ``tol``, m)
    moves only within it (its target clipped to the box); a node outside every box that
    would end up in one does not move.
    """
    from ...fem.elasticity import min_jacobian_determinants
    from ...fem.samples import lattice_spacing, lattice_surface
    from ...model.tetrahedra import TetMesh

    x0 = np.asarray(nodes, dtype=float)
    mesh_nodes = np.asarray(mesh_nodes, dtype=float)
    surface = np.flatnonzero(lattice_surface(hexahedra, len(x0)))
    tet = TetMesh(mesh_nodes, tets)
    _, target, _ = tet.nearest_on_boundary(x0[surface])
    normal = outward_normals(hexahedra, len(x0))[surface]
    length = np.linalg.norm(normal, axis=1)
    pointed = length > 0  # opposite faces of a fin cancel: such a node takes its nearest point
    direction = np.zeros_like(normal)
    direction[pointed] = normal[pointed] / length[pointed, None]
    triangles = mesh_nodes[tet.boundary[0]]
    t = np.full(len(surface), np.inf)
    reach = RAY_REACH * float(np.min(lattice_spacing(x0, hexahedra)))
    t[pointed] = line_crossings(x0[surface][pointed], direction[pointed], triangles, reach)
    along = np.isfinite(t)
    target[along] = x0[surface][along] + t[along, None] * direction[along]
    share = np.ones(len(surface))
    boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes or []]

    def inside(x: np.ndarray) -> np.ndarray:
        """(B, S) each box's membership of the surface nodes at ``x`` (S, 3)."""
        return np.array(
            [np.all((x >= lo - tol) & (x <= hi + tol), axis=1) for lo, hi in boxes]
        ).reshape(len(boxes), len(x))

    held = inside(x0[surface])
    for (lo, hi), member in zip(boxes, held, strict=True):
        target[member] = np.clip(target[member], lo, hi)
    where = np.full(len(x0), -1)
    where[surface] = np.arange(len(surface))
    before = min_jacobian_determinants(x0[hexahedra])
    while True:
        x = x0.copy()
        x[surface] += share[:, None] * (target - x0[surface])
        strayed = np.any(inside(x[surface]) != held, axis=0)
        bad = min_jacobian_determinants(x[hexahedra]) < KEPT_JACOBIAN * before
        if not bad.any() and not strayed.any():
            return x
        share[strayed] = 0.0
        moved = where[np.unique(hexahedra[bad])]
        share[moved[moved >= 0]] *= 0.8


def conform_spec(spec: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """``spec`` (a ``voxels`` geometry with its tetrahedra in ``reference.mesh``, as
    :func:`spec_from_mesh` makes it) on the surface-conforming lattice
    (:func:`conform_lattice`): a hexahedral ``mesh`` geometry, the same nodes and hexahedra,
    the surface nodes on the mesh's surface; and notes.

    Every selector keeps the nodes it had on the voxels: a ``face`` (a plane of the voxels'
    bounding box, which a curved surface no longer has) becomes the box of the nodes within
    h/2 of that plane or beyond it (what the tetrahedral reference holds or loads for the face,
    :func:`fpm.fem.tet10.fixed_nodes`), an ``at`` the ``node`` it named; nodes in a box stay in
    it and nodes out of every box stay out. ``nearest`` and ``node`` selectors are kept as
    given.
    """
    from ...model.problem import load_problem

    mesh = (spec.get("reference") or {}).get("mesh")
    if spec["geometry"].get("type") != "voxels" or mesh is None:
        raise MeshError(
            "a conforming lattice moves a voxel lattice's surface onto its tetrahedral mesh's: "
            "give a tetrahedral mesh (not hexahedra, not a surface, not --voxel-reference)"
        )
    problem = load_problem(spec)
    x0 = problem.solid.nodes
    hexahedra = problem.solid.elements()
    assert hexahedra is not None
    h = float(min(spec["geometry"]["spacing"]))
    mesh_nodes = np.asarray(mesh["nodes"], dtype=float)
    tets = np.asarray(mesh["tetrahedra"])
    graded = graded_lattice(
        np.asarray(spec["geometry"]["occupancy"], dtype=bool),
        np.asarray(spec["geometry"]["origin"], dtype=float),
        h,
        mesh_nodes,
        tets,
    )
    if graded.refined:
        x0, hexahedra = graded.nodes, graded.hexahedra
    lo, hi = x0.min(axis=0), x0.max(axis=0)
    margin = np.max(hi - lo) + h
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    notes: list[str] = []
    rewritten: list[str] = []  # the selectors that had to change form

    def kept(selector: dict[str, Any]) -> dict[str, Any]:
        out = dict(selector)
        rewritten.extend(key for key in ("face", "at") if key in out)
        if "face" in out:
            axis, side = "xyz".index(out["face"][0]), out.pop("face")[1]
            box_lo, box_hi = lo - margin, hi + margin
            if side == "-":
                box_hi[axis] = lo[axis] + 0.499 * h
            else:
                box_lo[axis] = hi[axis] - 0.499 * h
            out["box"] = [box_lo.tolist(), box_hi.tolist()]
        if "at" in out:
            found = np.linalg.norm(x0 - np.asarray(out.pop("at")), axis=1)
            out["node"] = int(np.argmin(found))
        if "box" in out:
            boxes.append((np.asarray(out["box"][0]), np.asarray(out["box"][1])))
        return out

    conformed = dict(spec)
    conformed["fixed"] = [kept(s) for s in spec["fixed"]]
    for key in ("load_cases", "validation_cases"):
        if key in spec:
            conformed[key] = [
                {**case, "forces": [kept(f) for f in case["forces"]]} for case in spec[key]
            ]
    if rewritten:
        notes.append(
            "conforming lattice: face selectors became the boxes of the nodes within h/2 of "
            "the face (the surface no longer has flat faces), 'at' selectors the nodes they "
            "named"
        )
    x = conform_lattice(x0, hexahedra, mesh_nodes, tets, boxes=boxes, tol=1e-3 * h)
    notes += refined_notes(graded)
    surface = np.any(x != x0, axis=1)
    notes.append(
        f"conforming lattice: {int(surface.sum())} surface nodes moved onto the mesh's surface "
        f"(up to {np.linalg.norm(x - x0, axis=1).max() / h:.2g} h), every hexahedron keeping "
        f"at least {KEPT_JACOBIAN:g} of its voxel's smallest Jacobian"
    )
    conformed["geometry"] = {
        "type": "mesh",
        "nodes": x.tolist(),
        "hexahedra": hexahedra.tolist(),
        "connectivity": spec["geometry"].get("connectivity", "full"),
    }
    if graded.refined:
        conformed["geometry"]["levels"] = graded.levels.tolist()
    return conformed, notes


def refined_notes(graded: GradedLattice) -> list[str]:
    """One line per part of ``graded`` refined: where, how many cells, how many nodes it took,
    and what is still one cell thick at h/2."""
    out = []
    for i, part in enumerate(graded.parts):
        refined = (
            f"h/2 over {part.cells} cells: {part.nodes_added} nodes"
            if part.with_part is None
            else f"h/2 with part {part.with_part + 1} (one region: its cells and nodes are "
            "counted there)"
        )
        line = (
            f"graded lattice: part {i + 1} one cell thick at h = {graded.spacing:.4g} m "
            f"({part.thin_cells} cells around {_fmt(part.centre)} m) refined to {refined}"
        )
        if part.still_thin:
            line += f"; {part.still_thin} of its cells are one cell thick at h/2 too (modelled so)"
        out.append(line)
    return out
