"""Which cell gives which spring what share of its family's k.

families+volume and everything built on it (material regions, the per-cell stiffness field)
assemble the springs from the lattice's cells, as an FEM assembles its elements: each cell
gives its 12 edges, 12 face diagonals and 4 body diagonals :data:`CELL_SHARE` of their
family's k (times 2^-L for a cell of level L of a graded lattice: k ~ mu h).
:func:`cell_shares` is that matching, once per problem; :mod:`fpm.model.stiffness`
sums it per spring (its assembly weights) or weights it per cell (the field), and
:mod:`fpm.model.materials` sums it per region.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .hexahedron import local_families, local_pairs
from .problem import Problem

CELL_SHARE = np.array([0.25, 0.5, 1.0])
"""Share of its family's k a cell gives each of its edges, face and body diagonals (an interior
edge is in 4 cells, a face diagonal in 2, a body diagonal in 1)."""


def cell_shares(problem: Problem) -> sp.csr_matrix:
    """(S, H) sparse: entry (s, c) is the :data:`CELL_SHARE` of spring s's family that cell c
    gives it (0 where s is not an edge or diagonal of c), springs in the solid's order, cells
    in its hexahedra's. Its row sums are :func:`fpm.model.stiffness.assembly_weights`; times
    per-cell factors, the field's springs (:func:`fpm.model.stiffness.field_stiffness`); times
    a region indicator, a region's (:func:`fpm.model.materials.region_weights`). Built once
    per problem.

    Raises:
        ValueError: the geometry is a network (no cells).
    """
    cached = problem.cache.cell_shares
    if cached is None:
        solid = problem.solid
        hexahedra = solid.elements()
        if hexahedra is None:
            raise ValueError("a network geometry has no cells to assemble springs from")
        connectivity = problem.spec.geometry.connectivity  # type: ignore[union-attr]
        pairs = local_pairs(connectivity)
        a = hexahedra[:, pairs[:, 0]].ravel()
        b = hexahedra[:, pairs[:, 1]].ravel()
        n = problem.n_nodes
        keys = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
        springs = solid.springs.astype(np.int64)
        spring_keys = springs[:, 0] * n + springs[:, 1]
        order = np.argsort(spring_keys)
        which = order[np.searchsorted(spring_keys, keys, sorter=order)]
        share = np.tile(CELL_SHARE[local_families(connectivity)], len(hexahedra))
        cell = np.repeat(np.arange(len(hexahedra)), len(pairs))
        if solid.levels is not None:  # a graded lattice: a cell of half the size, half the k
            share = share * 0.5 ** solid.levels.astype(float)[cell]
        cached = problem.cache.cell_shares = sp.csr_matrix(
            (share, (which, cell)), shape=(len(springs), len(hexahedra))
        )
    return cached
