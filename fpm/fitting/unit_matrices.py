"""The K_p of a perturbed list (:mod:`fpm.fitting.reduced`): the lattice's stiffness matrix
linearised at rest is ``K(theta) = sum_p theta_p K_p`` (K_p: the matrix of family p's
assembled springs at k = 1, and of the cells at kappa = 1), each kept as its nonzero 3x3
blocks (:class:`UnitMatrices`) and shared by the load cases and chains of one process
(:func:`unit_matrices`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..model.problem import Problem

SUM_PIECE = 1 << 16
"""Blocks per piece when K(theta) is summed (:meth:`UnitMatrices.at`)."""


@dataclass(frozen=True)
class _Unit:
    """One K_p: its nonzero 3x3 blocks, where they sit in the list's block pattern, and their
    own pattern (``scipy.sparse.bsr_matrix``'s indices and indptr)."""

    values: np.ndarray  # (b, 3, 3)
    positions: np.ndarray  # (b,) indices into the list's blocks
    indices: np.ndarray
    indptr: np.ndarray


@dataclass(frozen=True)
class UnitMatrices:
    """The K_p of one perturbed list, (3M, 3M) N/m each (M the list's free nodes), each kept as
    its nonzero 3x3 blocks only (a family's springs touch 7, 13 or 9 of the 27 blocks of a row,
    the cells all 27), and K(theta) = sum_p theta_p K_p formed as block values on the list's
    one block pattern (the springs' and cells'), not as a sum of sparse matrices (which would
    build several K(theta)-sized intermediates).

    Attributes:
        units: the K_p.
        n_blocks: blocks of the list's pattern; indices, indptr: that pattern.
    """

    units: tuple[_Unit, ...]
    n_blocks: int
    indices: np.ndarray
    indptr: np.ndarray

    @classmethod
    def of(cls, tangents: Iterable[sp.bsr_matrix]) -> UnitMatrices:
        """From the K_p assembled on one block pattern, taken one at a time (their zero blocks
        are dropped before the next is assembled)."""
        units: list[_Unit] = []
        indices = indptr = row = np.zeros(0, dtype=np.int32)
        n_blocks = 0
        for tangent in tangents:
            if not units:
                indices, indptr, n_blocks = tangent.indices, tangent.indptr, len(tangent.data)
                row = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
            assert np.array_equal(tangent.indices, indices)  # one block pattern
            positions = np.flatnonzero(np.any(tangent.data != 0.0, axis=(1, 2)))
            own = np.zeros_like(indptr)
            np.cumsum(np.bincount(row[positions], minlength=len(indptr) - 1), out=own[1:])
            units.append(
                _Unit(
                    values=np.ascontiguousarray(tangent.data[positions]),
                    positions=positions.astype(np.int32),
                    indices=np.ascontiguousarray(indices[positions]),
                    indptr=own,
                )
            )
        return cls(tuple(units), n_blocks, indices, indptr)

    def __len__(self) -> int:
        return len(self.units)

    def _bsr(self, data: np.ndarray, indices: np.ndarray, indptr: np.ndarray) -> sp.bsr_matrix:
        n = 3 * (len(indptr) - 1)
        return sp.bsr_matrix((data, indices, indptr), shape=(n, n), copy=False)

    def matrix(self, p: int) -> sp.bsr_matrix:
        """K_p on its own blocks (a view of the shared values: read only)."""
        u = self.units[p]
        return self._bsr(u.values, u.indices, u.indptr)

    def at(self, theta: np.ndarray) -> sp.bsr_matrix:
        """K(theta) = sum_p theta_p K_p (new values on the list's block pattern), summed a
        piece of :data:`SUM_PIECE` blocks at a time (whole, the products and the gathered
        blocks would be two more K(theta)-sized transients)."""
        values = np.zeros((self.n_blocks, 3, 3))
        for t, u in zip(np.asarray(theta, dtype=float), self.units, strict=True):
            for start in range(0, len(u.positions), SUM_PIECE):
                piece = slice(start, start + SUM_PIECE)
                values[u.positions[piece]] += t * u.values[piece]  # positions are distinct
        return self._bsr(values, self.indices, self.indptr)


_UNITS = threading.Lock()


def unit_matrices(
    problem: Problem, system: Any, units: list[Any], depth: int | None
) -> UnitMatrices:
    """The K_p of one perturbed list, linearised at rest: built once per (depth, list) and kept
    in ``problem.cache.reduced_units``, so that load cases with the same list and the chains
    running at once in one process share them (read only)."""
    key = (depth, system.free.tobytes())
    with _UNITS:
        kept = problem.cache.reduced_units
        if kept is None:
            kept = problem.cache.reduced_units = {}
        if key not in kept:
            rest = np.zeros((system.n_free, 3))
            kept[key] = UnitMatrices.of(
                system.tangent(rest, system.parameters(s), modified=True) for s in units
            )
        return kept[key]
