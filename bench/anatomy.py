"""Organ meshes with thin parts for the tests and benches: real anatomy the project did not
draw, meshed as a user's pipeline would, and three shapes it generates.

Real anatomy: the frog tissue segmentation that ships inside pyvista's wheel, one tissue's mask
turned into tetrahedra (:mod:`bench.frog`). Generated: a lobe tapering to an edge, a hollow
organ's closed wall, a body with a thin tapering appendage, each with its analytic volume
(:mod:`bench.shapes`).

:data:`ORGANS` names each with its mesh builder, the fixed nodes and five presses (two fitted,
three unseen) in the short forms ``fpmcal spec from-mesh --fix/--force/--validate`` take::

    from bench.anatomy import ORGANS
    organ = ORGANS["frog liver"]
    mesh = organ.mesh()  # meshio.Mesh, m
    presses = organ.presses(mesh)  # {"fix": [...], "forces": [...], "validation": [...]}
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import meshio
import numpy as np

from bench import frog
from bench.frog import FROG_VTI, PYVISTA, frog_labels, frog_organ
from bench.shapes import (
    LIMB,
    LOBE,
    LONGEST,
    _positive,
    hollow,
    hollow_volume,
    limb,
    limb_radius,
    limb_volume,
    lobe,
    lobe_volume,
)
from fpm.model.tetrahedra import DEGENERATE, FACES, TetMesh

YOUNGS = 5e3
"""Young's modulus the presses are sized for, Pa."""
STRAIN = 0.03
"""The presses' nominal strain: force = STRAIN * YOUNGS * (LONGEST / 10)^2 (0.06 N)."""


@dataclass(frozen=True)
class MeshCheck:
    """What a tetrahedral mesh is: counts, volume (m^3), extent (3,) m, the smallest tetrahedron's
    volume over its longest edge cubed (``DEGENERATE`` and below is flat), the number of
    face-connected pieces, boundary edges not shared by exactly two boundary triangles (0: the
    surface is closed) and the surface's separate sheets (1 for a solid, 2 for a closed
    wall)."""

    nodes: int
    tetrahedra: int
    volume: float
    extent: tuple[float, float, float]
    worst_shape: float
    pieces: int
    open_edges: int
    sheets: int

    @property
    def valid(self) -> bool:
        """Positive, not flat, one piece, closed."""
        return self.worst_shape > DEGENERATE and self.pieces == 1 and self.open_edges == 0


def check(mesh: meshio.Mesh) -> MeshCheck:
    """The :class:`MeshCheck` of a mesh's tetrahedra."""
    import scipy.sparse as sp

    nodes = np.asarray(mesh.points, dtype=float)
    tets = mesh.get_cells_type("tetra")
    tet = TetMesh(nodes, tets)
    volume, longest = tet.volumes, tet.longest_edges
    faces = np.sort(tets[:, FACES].reshape(-1, 3), axis=1)
    _, face_id = np.unique(faces, axis=0, return_inverse=True)
    owner = np.repeat(np.arange(len(tets)), 4)
    incidence = sp.coo_matrix((np.ones(len(owner)), (owner, face_id.ravel()))).tocsr()
    pieces, _ = sp.csgraph.connected_components(incidence @ incidence.T, directed=False)
    triangles, _ = tet.boundary
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, uses = np.unique(edges, axis=0, return_counts=True)
    graph = sp.coo_matrix((np.ones(len(unique)), unique.T), shape=(len(nodes),) * 2)
    on_surface = np.unique(triangles)
    sheets, label = sp.csgraph.connected_components(graph, directed=False)
    return MeshCheck(
        nodes=len(nodes),
        tetrahedra=len(tets),
        volume=float(volume.sum()),
        extent=tuple(float(e) for e in np.ptp(nodes, axis=0)),  # type: ignore[arg-type]
        worst_shape=float((volume / longest**3).min()),
        pieces=int(pieces),
        open_edges=int((uses != 2).sum()),
        sheets=len(np.unique(label[on_surface])) if sheets else 0,
    )


def surface_normals(mesh: meshio.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(S,) the boundary nodes and (S, 3) their outward unit normals (area-weighted)."""
    nodes = np.asarray(mesh.points, dtype=float)
    triangles, _ = TetMesh(nodes, _positive(nodes, mesh.get_cells_type("tetra"))).boundary
    a, b, c = (nodes[triangles[:, i]] for i in range(3))
    area_normal = np.cross(b - a, c - a)
    normals = np.zeros_like(nodes)
    for i in range(3):
        np.add.at(normals, triangles[:, i], area_normal)
    surface = np.unique(triangles)
    n = normals[surface]
    return surface, n / np.linalg.norm(n, axis=1, keepdims=True)


def _fmt(v: np.ndarray) -> str:
    """A vector as x,y,z with 4 significant digits, components below 1e-9 of its largest 0."""
    v = np.asarray(v, dtype=float)
    v = np.where(np.abs(v) > 1e-9 * np.abs(v).max(), v, 0.0)
    return ",".join(f"{x:.4g}" for x in v)


def auto_presses(mesh: meshio.Mesh, held: float = 0.15) -> dict[str, list[str]]:
    """Fixed nodes and five presses for any organ lying on its bed: held, the nodes below
    ``held`` of its height (a box); pressed, surface nodes facing up (normal z > 0.3) in its
    upper half, the first the one nearest the top's centre, the others each the farthest from
    those before (fitted: the first two; unseen: the other three), each pushed along its inward
    normal with STRAIN * YOUNGS * (LONGEST / 10)^2 N."""
    nodes = np.asarray(mesh.points, dtype=float)
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    surface, normal = surface_normals(mesh)
    up = (normal[:, 2] > 0.3) & (nodes[surface, 2] > lo[2] + 0.5 * (hi[2] - lo[2]))
    points, normal = nodes[surface[up]], normal[up]
    top = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    chosen = [int(np.argmin(np.linalg.norm(points - top, axis=1)))]
    for _ in range(4):
        gap = np.min([np.linalg.norm(points - points[i], axis=1) for i in chosen], axis=0)
        chosen.append(int(np.argmax(gap)))
    force = STRAIN * YOUNGS * (LONGEST / 10) ** 2
    presses = [f"nearest:{_fmt(points[i])}:{_fmt(-force * normal[i])}" for i in chosen]
    below = lo[2] + held * (hi[2] - lo[2])
    fix = f"box:{_fmt(lo - 1)}:{_fmt(np.array([hi[0] + 1, hi[1] + 1, below]))}"
    return {"fix": [fix], "forces": presses[:2], "validation": presses[2:]}


def _press(point: list[float], direction: list[float], scale: float = 1.0) -> str:
    force = STRAIN * YOUNGS * (LONGEST / 10) ** 2 * scale
    d = np.asarray(direction, float)
    return f"nearest:{_fmt(np.asarray(point))}:{_fmt(force * d / np.linalg.norm(d))}"


def lobe_presses(mesh: meshio.Mesh) -> dict[str, list[str]]:
    """The lobe held at its root (x below 15% of its length), pressed down on its upper face at
    a quarter and at half its length (fitted), and at 0.4 and 0.65 of it off the midline and
    sideways at its middle (unseen); the forces scaled with the square of the thickness there
    over the root's (the same strain)."""
    length, width, root, edge = (LOBE[k] for k in ("length", "width", "thick", "edge"))

    def top(x: float, y: float) -> list[float]:
        return [x, y, (root + (edge - root) * x / length) * (1 - (2 * y / width) ** 2 / 2)]

    def scale(x: float) -> float:
        return float(((root + (edge - root) * x / length) / root) ** 2)

    fitted = [_press(top(a * length, 0), [0, 0, -1], scale(a * length)) for a in (0.25, 0.5)]
    unseen = [
        _press(top(0.4 * length, 0.3 * width), [0, 0, -1], scale(0.4 * length)),
        _press(top(0.65 * length, -0.2 * width), [0, 0, -1], scale(0.65 * length)),
        _press([0.5 * length, width / 2, top(0.5 * length, width / 2)[2] / 2], [0, -1, 0],
               scale(0.5 * length)),
    ]  # fmt: skip
    return {"fix": [f"box:-1,-1,-1:{0.15 * length:.4g},1,1"], "forces": fitted,
            "validation": unseen}  # fmt: skip


def limb_presses(mesh: meshio.Mesh) -> dict[str, list[str]]:
    """The limb held by its body's underside (z below 15% of its height), pressed down on the
    body's top and the appendage's top at 60% of its length (fitted), and at the body's side, the
    appendage's top near its root and sideways near its tip (unseen); the forces on the
    appendage scaled with the square of its radius there over the body's."""
    r0 = LIMB["radius"]

    def on_top(x: float) -> list[float]:
        return [x, 0.0, r0 + float(limb_radius(np.array(x)))]

    def scale(x: float) -> float:
        return float(min(1.0, (float(limb_radius(np.array(x))) / r0) ** 2))

    tail = LIMB["body"] + np.array([0.6, 0.15, 0.8]) * (LONGEST - LIMB["body"])
    fitted = [_press(on_top(LIMB["body"] / 2), [0, 0, -1]),
              _press(on_top(tail[0]), [0, 0, -1], scale(tail[0]))]  # fmt: skip
    side = LIMB["body"] * 0.4
    unseen = [
        _press([side, float(limb_radius(np.array(side))), r0], [0, -1, 0]),
        _press(on_top(tail[1]), [0, 0, -1], scale(tail[1])),
        _press([tail[2], float(limb_radius(np.array(tail[2]))), r0], [0, -1, 0], scale(tail[2])),
    ]
    return {"fix": [f"box:-1,-1,-1:1,1,{0.3 * r0:.4g}"], "forces": fitted, "validation": unseen}


@dataclass(frozen=True)
class Organ:
    """One organ mesh of the registry: ``mesh()`` builds it (a ``meshio.Mesh``, m, tetrahedra),
    ``presses(mesh)`` gives its fixed nodes and presses as ``fpmcal spec from-mesh`` takes them
    (``{"fix": [...], "forces": [two fitted], "validation": [three unseen]}``); ``volume`` is
    its analytic volume, m^3, where it has one; ``needs`` the modules its builder imports
    beyond the product's (the ``anatomy`` extra)."""

    name: str
    mesh: Callable[[], meshio.Mesh]
    presses: Callable[[meshio.Mesh], dict[str, list[str]]] = auto_presses
    volume: float | None = None
    needs: tuple[str, ...] = field(default=())
    thin: str = ""


FROG_ORGANS = {"liver": 4, "kidney": 3, "stomach": 3, "heart": 3, "lung": 3, "spleen": 2}
"""The frog's tissues in :data:`ORGANS`, each with its marching-cubes step (voxels): the
largest coarser, the stomach's thin wall at 3 (at 4 its flattest tetrahedra are 200 times
flatter), the small spleen finer."""

ORGANS: dict[str, Organ] = {
    "lobe": Organ("lobe", lobe, lobe_presses, lobe_volume(), thin="its edge, 2 mm"),
    "hollow": Organ("hollow", hollow, auto_presses, hollow_volume(),
                    thin="its wall, 5.6-8 mm"),
    "limb": Organ("limb", limb, limb_presses, limb_volume(), thin="its appendage's tip, 4 mm"),
    **{
        f"frog {t}": Organ(f"frog {t}", lambda t=t, s=s: frog_organ(t, s),  # type: ignore[misc]
                           needs=("skimage", "gmsh"), thin="as segmented")
        for t, s in FROG_ORGANS.items()
    },
}  # fmt: skip
"""Organ name -> :class:`Organ` (module docstring)."""


def describe() -> list[dict[str, Any]]:
    """Each organ of :data:`ORGANS` made afresh (the frog's in a scratch folder, the label volume
    read first, its seconds apart) and checked: name, counts, volume, validity, seconds, presses;
    each also recorded for ``bench/results/anatomy.json``. The frog meshes are then kept in
    :data:`bench.frog.CACHE`."""
    import shutil
    import tempfile
    import time

    from bench import results

    start = time.perf_counter()
    frog_labels()
    results.record("anatomy", "frog labels", seconds=time.perf_counter() - start,
                   wheel=PYVISTA, file=FROG_VTI)  # fmt: skip
    rows = []
    kept, frog.CACHE = frog.CACHE, Path(tempfile.mkdtemp(prefix="fpm-anatomy-"))
    try:
        for name, organ in ORGANS.items():
            start = time.perf_counter()
            mesh = organ.mesh()
            seconds = time.perf_counter() - start
            found = check(mesh)
            row = {
                "name": name,
                **found.__dict__,
                "valid": found.valid,
                "seconds": seconds,
                "analytic_volume": organ.volume,
                "thin": organ.thin,
                **organ.presses(mesh),
            }
            results.record("anatomy", "meshes", **row)
            rows.append(row)
        kept.mkdir(parents=True, exist_ok=True)
        for path in frog.CACHE.glob("*.vtu"):
            shutil.move(str(path), kept / path.name)
    finally:
        shutil.rmtree(frog.CACHE, ignore_errors=True)
        frog.CACHE = kept
    return rows


if __name__ == "__main__":
    from bench import results

    for row in describe():
        print(
            f"{row['name']:14s} {row['nodes']:6d} nodes {row['tetrahedra']:6d} tetrahedra "
            f"{row['volume'] * 1e6:7.1f} cm^3 valid {row['valid']} {row['seconds']:5.1f} s"
        )
    results.save("anatomy", "python -m bench.anatomy")
