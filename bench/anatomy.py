"""Organ meshes with thin parts for the tests and benches: real anatomy the project did not
draw, meshed as a user's pipeline would, and three shapes it generates.

Real anatomy: the frog tissue segmentation (a 500 x 470 x 136 label volume, voxels 1 x 1 x 1.5
mm; the tissue numbering of VTK's frog examples, :data:`FROG_TISSUES`) that ships inside
pyvista's wheel as ``pyvista/examples/frog_tissues.vti``. :func:`frog_labels` fetches the wheel
with pip (``pip download --no-deps``, into :data:`CACHE`) and reads the file with
:func:`read_vti`, a reader of VTK XML ImageData with inline zlib-compressed binary data, so
neither pyvista nor VTK is needed. :func:`frog_organ` turns one tissue's mask into tetrahedra:
the largest connected piece, its cavities filled, a light Gaussian smoothing (1.5 mm) and
marching cubes (scikit-image) on every ``step``-th voxel, a Taubin smoothing of the surface
(its marching-cubes triangles would otherwise make flat tetrahedra), scaled to
:data:`LONGEST` along its longest side, then Gmsh's 3D mesher (Delaunay, optimised) inside that
surface, which it keeps. The optional extra ``anatomy`` (``pip install -e '.[anatomy]'``)
brings scikit-image and gmsh.

Generated: :func:`lobe` (a lobe tapering to an edge), :func:`hollow` (a hollow organ's closed
wall), :func:`limb` (a body with a thin tapering appendage), each a structured grid of Kuhn
tetrahedra mapped onto the shape (pure NumPy), with its analytic volume.

:data:`ORGANS` names each with its mesh builder, the fixed nodes and five presses (two fitted,
three unseen) in the short forms ``fpmcal spec from-mesh --fix/--force/--validate`` take::

    from bench.anatomy import ORGANS
    organ = ORGANS["frog liver"]
    mesh = organ.mesh()  # meshio.Mesh, m
    presses = organ.presses(mesh)  # {"fix": [...], "forces": [...], "validation": [...]}
"""

from __future__ import annotations

import base64
import os
import subprocess
import sys
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import meshio
import numpy as np

from bench.tet_organ import KUHN, cube_to_ball
from fpm.model.tetrahedra import DEGENERATE, FACES, TetMesh, signed_volumes

LONGEST = 0.2
"""Every organ's longest side, m."""
CACHE = Path(os.environ.get("FPM_ANATOMY_CACHE", "~/.cache/fpm-anatomy")).expanduser()
"""Where the pyvista wheel and the frog meshes are kept (``FPM_ANATOMY_CACHE`` overrides)."""
PYVISTA = "pyvista==0.49.2"
"""The wheel that carries the frog tissues."""
FROG_VTI = "pyvista/examples/frog_tissues.vti"
FROG_TISSUES = {
    1: "blood", 2: "brain", 3: "duodenum", 4: "eye retina", 5: "eye white", 6: "heart",
    7: "ileum", 8: "kidney", 9: "large intestine", 10: "liver", 11: "lung", 12: "nerve",
    13: "skeleton", 14: "spleen", 15: "stomach",
}  # fmt: skip
"""Tissue label -> name (labels 16-29 are specks of a few voxels)."""
YOUNGS = 5e3
"""Young's modulus the presses are sized for, Pa."""
STRAIN = 0.03
"""The presses' nominal strain: force = STRAIN * YOUNGS * (LONGEST / 10)^2 (0.06 N)."""

_VTK_TYPES = {
    "Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
    "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8",
}  # fmt: skip


# ------------------------------------------------------------------ the frog's tissues


def read_vti(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first point array of a VTK XML ImageData file's bytes (inline ``binary`` data,
    uncompressed or ``vtkZLibDataCompressor``, header UInt32 or UInt64): (nx, ny, nz) values
    (x varies fastest in the file), the origin (3,) and the spacing (3,), in the file's units.

    Raises:
        ValueError: the file is not such ImageData (the attribute at fault named).
    """
    root = ElementTree.fromstring(data)
    if root.get("type") != "ImageData":
        raise ValueError(f"VTKFile type {root.get('type')!r}: expected ImageData")
    order = "<" if root.get("byte_order", "LittleEndian") == "LittleEndian" else ">"
    header = order + {"UInt32": "u4", "UInt64": "u8"}[root.get("header_type", "UInt32")]
    compressor = root.get("compressor")
    if compressor not in (None, "vtkZLibDataCompressor"):
        raise ValueError(f"compressor {compressor!r}: only vtkZLibDataCompressor is read")
    image = root.find("ImageData")
    array = root.find("ImageData/Piece/PointData/DataArray")
    if image is None or array is None:
        raise ValueError("no ImageData/Piece/PointData/DataArray element")
    if array.get("format") != "binary":
        raise ValueError(f"DataArray format {array.get('format')!r}: only binary is read")
    extent = np.array(image.get("WholeExtent", "").split(), dtype=int)
    shape = tuple(int(n) for n in extent[1::2] - extent[::2] + 1)
    components = int(array.get("NumberOfComponents", "1"))
    dtype = np.dtype(order + _VTK_TYPES[array.get("type", "")])
    text = "".join((array.text or "").split()).encode()
    size = np.dtype(header).itemsize
    if compressor is None:
        raw = base64.b64decode(text)[size:]
    else:
        blocks = int(np.frombuffer(base64.b64decode(text[: 4 * -(-size // 3)])[:size], header)[0])
        chars = 4 * -(-(3 + blocks) * size // 3)  # the header is base64-encoded on its own
        sizes = np.frombuffer(base64.b64decode(text[:chars]), header)[3:].astype(np.int64)
        body = base64.b64decode(text[chars:])
        ends = np.cumsum(sizes)
        raw = b"".join(zlib.decompress(body[e - s : e]) for s, e in zip(sizes, ends, strict=True))
    values = np.frombuffer(raw, dtype)
    expected = int(np.prod(shape)) * components
    if values.size != expected:
        raise ValueError(f"DataArray holds {values.size} values, WholeExtent needs {expected}")
    values = values.reshape(shape[::-1] + ((components,) if components > 1 else ()))
    origin = np.array(image.get("Origin", "0 0 0").split(), dtype=float)
    spacing = np.array(image.get("Spacing", "1 1 1").split(), dtype=float)
    return np.moveaxis(values, [0, 1, 2], [2, 1, 0]), origin, spacing


def pyvista_wheel() -> Path:
    """pyvista's wheel in :data:`CACHE`, fetched with pip once (about 2.7 MB)."""
    wheels = sorted(CACHE.glob(f"pyvista-{PYVISTA.split('==')[1]}-*.whl"))
    if not wheels:
        CACHE.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--no-deps", "-q", PYVISTA, "-d", str(CACHE)],
            check=True,
        )
        wheels = sorted(CACHE.glob(f"pyvista-{PYVISTA.split('==')[1]}-*.whl"))
    return wheels[0]


@cache
def frog_labels() -> tuple[np.ndarray, np.ndarray]:
    """(nx, ny, nz) tissue labels (uint8, :data:`FROG_TISSUES`) and the voxel size (3,), m."""
    with zipfile.ZipFile(pyvista_wheel()) as wheel:
        labels, _, spacing = read_vti(wheel.read(FROG_VTI))
    return np.ascontiguousarray(labels), spacing * 1e-3


def largest_piece(mask: np.ndarray) -> np.ndarray:
    """The largest face-connected piece of a boolean voxel mask."""
    from scipy import ndimage

    pieces, count = ndimage.label(mask)
    if count == 0:
        raise ValueError("the mask is empty")
    sizes = np.bincount(pieces.ravel())
    sizes[0] = 0
    return pieces == sizes.argmax()


def mask_surface(
    mask: np.ndarray, spacing: np.ndarray, step: int = 3, sigma: float = 1.5e-3
) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle surface of a voxel mask (x, y, z): (V, 3) vertices, m, from the mask's
    corner, and (F, 3) triangles, outward. The mask's largest piece with its cavities filled,
    smoothed (Gaussian, ``sigma`` m), cut again to its largest piece, marching cubes on every
    ``step``-th voxel, the surface's largest connected sheet, 20 Taubin steps (0.5, -0.53)."""
    import scipy.sparse as sp
    from scipy import ndimage
    from skimage import measure

    def smooth(m: np.ndarray, s: float) -> np.ndarray:
        return ndimage.gaussian_filter(m.astype(float), s / spacing)

    m = np.pad(largest_piece(mask), step + 3)
    m = ndimage.binary_fill_holes(largest_piece(smooth(m, sigma) > 0.5))
    verts, tris, _, _ = measure.marching_cubes(
        smooth(m, 0.5 * spacing.min()), 0.5, spacing=tuple(spacing), step_size=step
    )
    edges = tris[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(edges)), edges.T), shape=(len(verts),) * 2).tocsr()
    graph = ((graph + graph.T) > 0).astype(float)
    _, sheet = sp.csgraph.connected_components(graph, directed=False)
    tris = tris[sheet[tris[:, 0]] == np.bincount(sheet[tris[:, 0]]).argmax()]
    used, tris = np.unique(tris, return_inverse=True)
    tris = tris.reshape(-1, 3)
    verts, graph = verts[used], graph[used][:, used]
    mean = sp.diags(1 / np.asarray(graph.sum(axis=1)).ravel()) @ graph
    for _ in range(20):
        for factor in (0.5, -0.53):
            verts = verts + factor * (mean @ verts - verts)
    return verts, tris


def tetrahedralise(verts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes and (T, 4) positive tetrahedra filling a closed triangle surface, by Gmsh
    (Delaunay, then its and Netgen's optimisers; the surface's triangles kept as they are, the
    interior graded from their size)."""
    import gmsh

    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("organ")
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(verts) + 1), verts.ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (tris + 1).ravel())
        loop = gmsh.model.geo.addSurfaceLoop([surface])
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, corners = gmsh.model.mesh.getElementsByType(4)
    finally:
        gmsh.finalize()
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets = index[corners.astype(np.int64)].reshape(-1, 4)
    used, tets = np.unique(tets, return_inverse=True)
    return coords.reshape(-1, 3)[used], _positive(coords.reshape(-1, 3)[used], tets.reshape(-1, 4))


def frog_organ(tissue: str, step: int = 3) -> meshio.Mesh:
    """The frog's ``tissue`` (a name of :data:`FROG_TISSUES`) as tetrahedra, m, its longest side
    :data:`LONGEST`, lowest corner at the origin; made once and kept in :data:`CACHE` as
    ``frog-TISSUE-sSTEP.vtu`` (module docstring; needs the ``anatomy`` extra)."""
    path = CACHE / f"frog-{tissue.replace(' ', '-')}-s{step}.vtu"
    if path.exists():
        return meshio.read(path)
    label = {name: k for k, name in FROG_TISSUES.items()}[tissue]
    labels, spacing = frog_labels()
    from scipy import ndimage

    box = ndimage.find_objects(labels, max_label=label)[label - 1]
    verts, tris = mask_surface(labels[box] == label, spacing, step)
    verts = (verts - verts.min(axis=0)) * (LONGEST / np.ptp(verts, axis=0).max())
    nodes, tets = tetrahedralise(verts, tris)
    mesh = meshio.Mesh(nodes, [("tetra", tets)])
    CACHE.mkdir(parents=True, exist_ok=True)
    meshio.write(path, mesh)
    return mesh


# ------------------------------------------------------------------ generated organs


def _positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """``tets`` with the inside-out ones renumbered."""
    tets = tets.copy()
    inverted = signed_volumes(nodes[tets]) < 0
    tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
    return tets


def grid_tetrahedra(
    cells: tuple[int, int, int], keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nodes of the unit cube's grid of ``cells`` and (T, 4) Kuhn tetrahedra (6 per cell)
    of the cells ``keep`` (a boolean array of shape ``cells``; all by default), the unused nodes
    dropped."""
    nx, ny, nz = cells
    axes = [np.linspace(0, 1, n + 1) for n in cells]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.nonzero(np.ones(cells, bool) if keep is None else keep)
    corners = np.stack(
        [
            idx[i, j, k], idx[i + 1, j, k], idx[i + 1, j + 1, k], idx[i, j + 1, k],
            idx[i, j, k + 1], idx[i + 1, j, k + 1], idx[i + 1, j + 1, k + 1], idx[i, j + 1, k + 1],
        ],
        axis=1,
    )  # fmt: skip
    used, tets = np.unique(corners[:, KUHN].reshape(-1, 4), return_inverse=True)
    return grid[used], tets.reshape(-1, 4)


def _square_to_disk(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of [-1, 1]^2 onto the unit disk (smooth, one to one, the square's sides onto the
    circle)."""
    return u * np.sqrt(1 - v**2 / 2), v * np.sqrt(1 - u**2 / 2)


LOBE = {"length": LONGEST, "width": 0.12, "thick": 0.3 * LONGEST, "edge": 0.01 * LONGEST}
"""The lobe's length (x), width (y), thickness at its root and at its edge, m."""


def lobe(cells: tuple[int, int, int] = (32, 16, 4)) -> meshio.Mesh:
    """A lobe tapering to an edge: over x in [0, length] its thickness falls linearly from
    ``thick`` (30% of its length) at the root to ``edge`` (1%) at the rim, across y in
    [-width/2, width/2] it thins as 1 - (2y/width)^2 / 2; the underside is the plane z = 0
    (:data:`LOBE`)."""
    grid, tets = grid_tetrahedra(cells)
    u, v, w = grid.T
    x = LOBE["length"] * u
    y = LOBE["width"] * (v - 0.5)
    root, edge = LOBE["thick"], LOBE["edge"]
    z = w * (root + (edge - root) * u) * (1 - (2 * y / LOBE["width"]) ** 2 / 2)
    nodes = np.stack([x, y, z], axis=1)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def lobe_volume() -> float:
    """The lobe's volume, m^3: length * width * (5/6) * (thick + edge) / 2."""
    return LOBE["length"] * LOBE["width"] * 5 / 6 * (LOBE["thick"] + LOBE["edge"]) / 2


HOLLOW: dict[str, Any] = {"semi_axes": (0.1, 0.08, 0.07), "wall": 0.08}
"""The hollow organ's outer semi-axes, m, and its wall as a fraction of them (an inner
ellipsoid of semi-axes (1 - wall) times the outer's: a wall 4% of the diameter across each
axis)."""


def hollow(cells: int = 14, layers: int = 2) -> meshio.Mesh:
    """A hollow organ's closed wall (a bladder, a stomach): the shell between two ellipsoids
    (:data:`HOLLOW`), ``layers`` tetrahedra deep. The cube's grid of ``cells``^3 less its inner
    cells, each point sent along its cube-to-ball direction (:func:`bench.tet_organ.cube_to_ball`
    of its projection onto the cube's surface) to the radius its layer gives."""
    n = cells
    index = np.arange(n)
    depth = np.minimum(index, n - 1 - index)
    keep = np.minimum.outer(np.minimum.outer(depth, depth), depth) < layers
    grid, tets = grid_tetrahedra((n, n, n), keep)
    p = 2 * grid - 1
    level = np.abs(p).max(axis=1)  # 1 on the outer surface, 1 - 2 layers / n on the inner
    direction = cube_to_ball(p / level[:, None])
    inner = 1 - 2 * layers / n
    radius = 1 - HOLLOW["wall"] * (1 - level) / (1 - inner)
    nodes = direction * radius[:, None] * np.asarray(HOLLOW["semi_axes"])
    nodes -= nodes.min(axis=0)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def hollow_volume() -> float:
    """The wall's volume, m^3: 4/3 pi a b c (1 - (1 - wall)^3)."""
    a, b, c = HOLLOW["semi_axes"]
    return 4 / 3 * np.pi * a * b * c * (1 - (1 - HOLLOW["wall"]) ** 3)


LIMB = {"body": 0.11, "radius": 0.04, "end": 0.15, "tip": 0.002}
"""The limb's body length and greatest radius, the share of that radius its ends keep (as the
square root of ``end``, 0.39), and the appendage's tip radius, m (its length: the rest of
:data:`LONGEST`)."""


def limb_radius(x: np.ndarray) -> np.ndarray:
    """The limb's radius at x, m: the body over [0, body] an ellipsoid's, kept above
    sqrt(end) times its greatest at the ends, then the appendage tapering linearly to ``tip``
    at LONGEST."""
    c, r = LIMB["body"] / 2, LIMB["radius"]
    body = r * np.sqrt(np.maximum(1 - (1 - LIMB["end"]) * ((x - c) / c) ** 2, LIMB["end"]))
    join = r * np.sqrt(LIMB["end"])
    t = (x - LIMB["body"]) / (LONGEST - LIMB["body"])
    return np.where(x <= LIMB["body"], body, join + (LIMB["tip"] - join) * t)


def limb(cells: tuple[int, int] = (44, 6)) -> meshio.Mesh:
    """A body with a thin tapering appendage (a limb, a tail): a solid of revolution about the
    x axis of radius :func:`limb_radius`, ``cells[0]`` tetrahedra along it (the body's and the
    appendage's lengths split in proportion) and ``cells[1]`` across, its cross-section the
    square mapped onto the disk."""
    along, across = cells
    grid, tets = grid_tetrahedra((along, across, across))
    u, v, w = grid.T
    x = LONGEST * u
    y, z = _square_to_disk(2 * v - 1, 2 * w - 1)
    r = limb_radius(x)
    nodes = np.stack([x, r * y, r * z + LIMB["radius"]], axis=1)
    return meshio.Mesh(nodes, [("tetra", _positive(nodes, tets))])


def limb_volume() -> float:
    """The limb's volume, m^3: pi r^2 integrated along x (body and cone in closed form)."""
    c, r = LIMB["body"] / 2, LIMB["radius"]
    body = np.pi * r**2 * 2 * c * (1 - (1 - LIMB["end"]) / 3)
    r0, r1, length = r * np.sqrt(LIMB["end"]), LIMB["tip"], LONGEST - LIMB["body"]
    return float(body + np.pi * length * (r0**2 + r0 * r1 + r1**2) / 3)


# ------------------------------------------------------------------ checks and presses


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
    :data:`CACHE`."""
    import shutil
    import tempfile
    import time

    from bench import results

    global CACHE
    start = time.perf_counter()
    frog_labels()
    results.record("anatomy", "frog labels", seconds=time.perf_counter() - start,
                   wheel=PYVISTA, file=FROG_VTI)  # fmt: skip
    rows = []
    kept, CACHE = CACHE, Path(tempfile.mkdtemp(prefix="fpm-anatomy-"))
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
        for path in CACHE.glob("*.vtu"):
            shutil.move(str(path), kept / path.name)
    finally:
        shutil.rmtree(CACHE, ignore_errors=True)
        CACHE = kept
    return rows


if __name__ == "__main__":
    from bench import results

    for row in describe():
        print(
            f"{row['name']:14s} {row['nodes']:6d} nodes {row['tetrahedra']:6d} tetrahedra "
            f"{row['volume'] * 1e6:7.1f} cm^3 valid {row['valid']} {row['seconds']:5.1f} s"
        )
    results.save("anatomy", "python -m bench.anatomy")
