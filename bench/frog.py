"""The frog's organs (:mod:`bench.anatomy`): real anatomy the project did not draw, meshed as a
user's pipeline would.

Their source: the frog tissue segmentation (a 500 x 470 x 136 label volume, voxels 1 x 1 x
1.5 mm; the tissue numbering of VTK's frog examples, :data:`FROG_TISSUES`) that ships inside
pyvista's wheel as ``pyvista/examples/frog_tissues.vti``. :func:`frog_labels` fetches the wheel
with pip (``pip download --no-deps``, into :data:`CACHE`) and reads the file with
:func:`read_vti`, a reader of VTK XML ImageData with inline zlib-compressed binary data, so
neither pyvista nor VTK is needed. :func:`frog_organ` turns one tissue's mask into tetrahedra:
the largest connected piece, its cavities filled, a light Gaussian smoothing (1.5 mm) and
marching cubes (scikit-image) on every ``step``-th voxel, a Taubin smoothing of the surface
(its marching-cubes triangles would otherwise make flat tetrahedra), scaled to
:data:`bench.shapes.LONGEST` along its longest side, then Gmsh's 3D mesher (Delaunay,
optimised) inside that surface, which it keeps. The optional extra ``anatomy``
(``pip install -e '.[anatomy]'``) brings scikit-image and gmsh.
"""

from __future__ import annotations

import base64
import os
import subprocess
import sys
import zipfile
import zlib
from functools import cache
from pathlib import Path
from xml.etree import ElementTree

import meshio
import numpy as np

from bench.shapes import LONGEST, _positive

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


_VTK_TYPES = {
    "Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
    "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8",
}  # fmt: skip


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
