"""A graded lattice: the voxels refined 2x2x2 where the solid is one cell across.

A tapering rim is one cell thick at every spacing: where the solid's thickness grows like
t(s) = a s from an edge, the strip with t < 2h is 2h/a wide for any h. A single layer of cells
cannot bend (one layer of 8-node cells has no through-thickness gradient; it locks as the
hexahedron does in shear) and the surface-conforming lattice squashes it onto both of the
mesh's faces at once. So where the voxels at spacing h leave a part one cell across
(:data:`fpm.model.geometry.THIN_PART_CELLS` or more such cells together), those cells and
their neighbours are voxelised again at h/2 from the mesh itself: the part is then two cells
across (or more), and the rest of the solid keeps h.

Where a coarse cell meets four fine ones, the four fine faces' edge midpoints and centre
(*hanging* nodes) belong to the fine cells only: they are tied to the coarse side by the fine
cells' springs and volume terms, a graph like any other (the perturbed lists, the export and
every engine take it as it is; no constraint). Each cell's springs take the share of their
family's k that its size gives (k ~ mu h: a cell of level L gives 2^-L of it,
:func:`fpm.model.shares.cell_shares`), its volume term its own rest volume, its mass
``rho V / 8`` per corner. The interface is softer than the continuum across it (the hanging
nodes see only the fine side); the calibration fits the stiffness with it in place.

Cells are on the fine grid of spacing h/2 (integer coordinates); a coarse cell (i, j, k) of the
voxels spans fine coordinates 2 (i, j, k) to 2 (i, j, k) + 2. NumPy and SciPy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...model.geometry import THIN_PART_CELLS
from ...model.hexahedron import NATURAL
from .voxelise import centroid_cells, one_piece, voxelise_tetrahedra

THIN_RUN = 1
"""A cell is thin when the solid is at most this many cells across it along some axis (the run
of solid cells through it, :func:`run_lengths`)."""

BITS = (NATURAL > 0).astype(np.int64)
"""(8, 3) each local corner's offset (0 or 1 per axis) in :mod:`fpm.model.hexahedron` order."""

MAX_CLOSURE = 8
""":func:`graded_lattice` fills partial interfaces (a coarse face that one to three fine cells
cover) at most this many times (each fill can leave another face of the same cell partial)."""


@dataclass
class RefinedPart:
    """A part of the solid one cell across at the voxels' spacing, refined.

    Attributes:
        centre: (3,) the mean of its thin cells' centres, m.
        thin_cells: how many coarse cells were one cell across there.
        cells: how many coarse cells of the region were refined (the part and its neighbours).
        nodes_added: lattice nodes the refinement added there (the fine grid's nodes that are
            not coarse nodes).
        still_thin: fine cells still one cell across (at h/2) in groups of at least
            :data:`THIN_PART_CELLS`: the part is thinner than the finest level, modelled there.
        with_part: the index of an earlier part whose refined region this one's joined (their
            neighbourhoods touch), or None; its cells, nodes and still-thin cells are counted
            there, and are 0 here.
    """

    centre: np.ndarray
    thin_cells: int
    cells: int
    nodes_added: int = 0
    still_thin: int = 0
    with_part: int | None = None


@dataclass
class GradedLattice:
    """Nodes (N, 3), m; hexahedra (H, 8); levels (H,) 0 for cells of h, 1 for cells of h/2; the
    parts refined; the coarse spacing h, m."""

    nodes: np.ndarray
    hexahedra: np.ndarray
    levels: np.ndarray
    spacing: float
    parts: list[RefinedPart] = field(default_factory=list)

    @property
    def refined(self) -> bool:
        return bool(self.parts)


def run_lengths(occupancy: np.ndarray) -> np.ndarray:
    """(3, cx, cy, cz) per axis, the length of the run of occupied cells along that axis
    through each cell of ``occupancy`` (cx, cy, cz) bool (0 where empty)."""
    occ = np.asarray(occupancy, dtype=bool)
    out = np.zeros((3, *occ.shape), dtype=np.int64)
    for a in range(3):
        o = np.moveaxis(occ, a, -1).astype(np.int64)
        n = o.shape[-1]
        forward = np.zeros_like(o)  # occupied cells up to and including this one
        backward = np.zeros_like(o)
        for i in range(n):
            prev = forward[..., i - 1] if i else 0
            forward[..., i] = (prev + 1) * o[..., i]
        for i in reversed(range(n)):
            nxt = backward[..., i + 1] if i + 1 < n else 0
            backward[..., i] = (nxt + 1) * o[..., i]
        out[a] = np.moveaxis(np.where(o > 0, forward + backward - 1, 0), -1, a)
    return out


def thin_groups(occupancy: np.ndarray) -> list[np.ndarray]:
    """The thin parts of ``occupancy`` (cx, cy, cz): groups (joined through faces, edges or
    corners) of at least :data:`THIN_PART_CELLS` solid cells whose run along some axis is at most
    :data:`THIN_RUN` cells; each a (C, 3) array of cell indices, the largest first."""
    from scipy.ndimage import label

    runs = run_lengths(occupancy)
    thin = ((runs >= 1) & (runs <= THIN_RUN)).any(axis=0)
    labels, count = label(thin, structure=np.ones((3, 3, 3)))
    if not count:
        return []
    sizes = np.bincount(labels.ravel())[1:]
    order = [g for g in np.argsort(-sizes, kind="stable") if sizes[g] >= THIN_PART_CELLS]
    return [np.argwhere(labels == g + 1) for g in order]


def graded_lattice(
    occupancy: np.ndarray,
    origin: np.ndarray,
    spacing: float,
    mesh_nodes: np.ndarray,
    tets: np.ndarray,
) -> GradedLattice:
    """The lattice of the voxels ``occupancy`` (cx, cy, cz) bool at ``origin`` (3,) and
    ``spacing`` h (m), with its parts one cell across (:func:`thin_groups`) and their
    neighbouring cells voxelised again at h/2 from the tetrahedra ``tets`` (T, 4) on
    ``mesh_nodes`` (M, 3): a cell of h/2 is solid when its centre lies in a tetrahedron, as a
    voxel is (:func:`~fpm.io.meshes.voxelise.voxelise_tetrahedra`), or, within a solid coarse
    cell, when a tetrahedron has a point inside it (:func:`_between_centres`).

    The refined region is the thin parts' cells and their solid neighbours (26 around). Where
    one to three of the four fine cells against a face shared with a solid coarse cell are
    solid, the others are made solid too (at most :data:`MAX_CLOSURE` passes), so every
    interface is a whole coarse face (:func:`fpm.model.geometry.graded_interfaces`); then the
    largest piece joined through faces is kept (as the voxels keep theirs). Without a thin
    part, the voxels' own nodes and hexahedra (level 0 everywhere), in
    :func:`fpm.model.geometry.voxel_mesh`'s order.
    """
    occ = np.asarray(occupancy, dtype=bool)
    origin = np.asarray(origin, dtype=float)
    groups = thin_groups(occ)
    if not groups:
        return _assemble(occ, np.zeros_like(occ), np.zeros((0, 0, 0), bool), origin, spacing, [])
    # One coarse cell of margin around the grid: a rim's fine cells may lie beyond the voxels.
    occ = np.pad(occ, 1)
    origin = origin - spacing
    groups = [g + 1 for g in groups]
    fine, _ = voxelise_tetrahedra(
        mesh_nodes, tets, spacing / 2, grid=(origin, 2 * np.asarray(occ.shape))
    )
    fine |= _between_centres(occ, origin, spacing, mesh_nodes, tets)
    region = np.zeros_like(occ)
    for g in groups:
        region[tuple(g.T)] = True
    region = _dilate(region) & occ
    for _ in range(MAX_CLOSURE):
        partial = _partial_faces(occ & ~region, region, fine)
        if not partial.any():
            break
        fine |= partial
    solid = np.repeat(np.repeat(np.repeat(occ & ~region, 2, 0), 2, 1), 2, 2)
    solid |= fine & np.repeat(np.repeat(np.repeat(region, 2, 0), 2, 1), 2, 2)
    solid, _ = one_piece(solid)
    coarse = occ & ~region & solid[::2, ::2, ::2]
    fine_cells = solid & np.repeat(np.repeat(np.repeat(region, 2, 0), 2, 1), 2, 2)
    parts = [
        RefinedPart(centre=origin + spacing * (g.mean(axis=0) + 0.5), thin_cells=len(g), cells=0)
        for g in groups
    ]
    return _assemble(coarse, fine_cells, region, origin, spacing, parts, groups)


def _between_centres(
    occ: np.ndarray, origin: np.ndarray, spacing: float, mesh_nodes: np.ndarray, tets: np.ndarray
) -> np.ndarray:
    """(2cx, 2cy, 2cz) bool: the cells of h/2 inside the solid coarse cells of ``occ`` that
    hold a point of a tetrahedron (:func:`~fpm.io.meshes.voxelise.centroid_cells`): a wall
    thinner than h/2 can pass between the fine cells' centres and would lose its cells."""
    held = centroid_cells(mesh_nodes, tets, spacing / 2, origin, 2 * np.asarray(occ.shape))
    return held & np.repeat(np.repeat(np.repeat(occ, 2, 0), 2, 1), 2, 2)


def _dilate(region: np.ndarray) -> np.ndarray:
    """``region`` grown by one cell into its 26 neighbours."""
    from scipy.ndimage import binary_dilation

    return np.asarray(binary_dilation(region, structure=np.ones((3, 3, 3))), dtype=bool)


def _partial_faces(coarse: np.ndarray, region: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """(2cx, 2cy, 2cz) bool: the fine cells of ``region`` cells (cx, cy, cz) against a face
    they share with a solid ``coarse`` cell where the two-by-two fine cells (of ``fine``)
    against that face are neither all solid nor all empty: the cells that make it whole."""
    cx, cy, cz = region.shape
    blocks = fine.reshape(cx, 2, cy, 2, cz, 2).transpose(0, 2, 4, 1, 3, 5)
    out = np.zeros_like(blocks)
    for a in range(3):
        for low in (True, False):  # the region cell's face at the low or the high end of a
            layer = np.take(blocks, 0 if low else 1, axis=3 + a)  # (cx, cy, cz, 2, 2)
            count = layer.sum(axis=(3, 4))
            # the coarse cell across that face: one cell lower (low face) or higher along a
            across = np.zeros_like(region)
            src, dst = [slice(None)] * 3, [slice(None)] * 3
            if low:
                src[a], dst[a] = slice(None, -1), slice(1, None)
            else:
                src[a], dst[a] = slice(1, None), slice(None, -1)
            across[tuple(dst)] = coarse[tuple(src)]
            partial = region & across & (count > 0) & (count < 4)
            index: list[int | slice] = [slice(None)] * 6
            index[3 + a] = 0 if low else 1
            view = out[tuple(index)]
            view |= partial[..., None, None]
    return out.transpose(0, 3, 1, 4, 2, 5).reshape(fine.shape)


def _assemble(
    coarse: np.ndarray,
    fine: np.ndarray,
    region: np.ndarray,
    origin: np.ndarray,
    spacing: float,
    parts: list[RefinedPart],
    groups: list[np.ndarray] | None = None,
) -> GradedLattice:
    """Nodes, hexahedra and levels of the solid ``coarse`` cells (cx, cy, cz) and ``fine``
    cells (2cx, 2cy, 2cz); corner nodes on the fine grid's integer coordinates, joined where
    they coincide."""
    big = np.argwhere(np.transpose(coarse, (2, 1, 0)))[:, ::-1]  # i fastest, as voxel_mesh
    small = np.argwhere(np.transpose(fine, (2, 1, 0)))[:, ::-1] if fine.size else big[:0]
    corners = np.concatenate(
        [
            (2 * big[:, None, :] + 2 * BITS[None]).reshape(-1, 3),
            (small[:, None, :] + BITS[None]).reshape(-1, 3),
        ]
    )
    keys, inverse = np.unique(corners, axis=0, return_inverse=True)
    hexahedra = inverse.reshape(-1, 8).astype(np.int64)
    nodes = origin + keys * (spacing / 2)
    levels = np.concatenate([np.zeros(len(big), np.int8), np.ones(len(small), np.int8)])
    if groups:
        _account(parts, groups, region, keys, small, hexahedra[len(big) :])
    return GradedLattice(nodes, hexahedra, levels, spacing, parts)


def _account(
    parts: list[RefinedPart],
    groups: list[np.ndarray],
    region: np.ndarray,
    keys: np.ndarray,
    small: np.ndarray,
    fine_hexahedra: np.ndarray,
) -> None:
    """Per refined part: the coarse cells of its region, the nodes it added (corners of its
    fine cells off the coarse grid) and its fine cells still one cell across."""
    from scipy.ndimage import label

    labels, _ = label(region, structure=np.ones((3, 3, 3)))
    cell_label = labels[tuple((small // 2).T)]  # (F,) the region piece of each fine cell
    added = np.any(keys % 2 == 1, axis=1)  # (N,) off the coarse grid
    fine = np.zeros(2 * np.asarray(region.shape), dtype=bool)
    fine[tuple(small.T)] = True
    thin = (run_lengths(fine) == 1).any(axis=0)[tuple(small.T)]
    first: dict[int, int] = {}  # region piece -> the first part refined in it
    for index, (part, g) in enumerate(zip(parts, groups, strict=True)):
        at = int(labels[tuple(g[0])])
        if at in first:  # one region with an earlier part: counted there, once
            part.with_part = first[at]
            continue
        first[at] = index
        part.cells = int((labels == at).sum())
        corners = np.unique(fine_hexahedra[cell_label == at])
        part.nodes_added = int(added[corners].sum())
        part.still_thin = int((thin & (cell_label == at)).sum())
