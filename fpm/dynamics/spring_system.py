"""The static solver's energy: the force terms of one perturbed list as functions of its free
nodes' displacements (:class:`SpringSystem`), and what the solvers of a problem share.

A system holds the springs with at least one free end and, when the model has the volume term,
the cells with at least one free corner (:mod:`fpm.dynamics.cell_terms`); held nodes stay at
their rest positions X. Over the displacements u (M, 3), m, of the M free nodes it evaluates

    E(u) = sum_s 1/2 k_s (|r_s| - L_s)^2 + sum_c W_c - sum_i F_i . u_i,     r_s = x_j - x_i,

x = X + u, k_s (N/m) the spring stiffness, L_s (m) its rest length, W_c the cells' energy and
F_i (N) the constant nodal forces; and its derivatives:

- gradient: dE/dx_j = k (|r| - L) n = -dE/dx_i (n = r / |r|), N; the unbalanced nodal force
  F_i + F_s of the dynamic run (:mod:`fpm.dynamics.voigt`) is minus the gradient;
- tangent of one spring (3x3, [[K, -K], [-K, K]] on its two nodes), N/m:
  K = k [n n^T + (1 - L/|r|) (I - n n^T)], indefinite where the spring is compressed; with the
  factor (1 - L/|r|) clamped at 0 ("modified") it is positive semi-definite. The assembled
  tangent is a (3M, 3M) BSR matrix of 3x3 node blocks on a pattern built once;
- energy changes E(u + step) - E(u) computed without cancellation
  (:meth:`SpringSystem.energy_change`), for the line searches;
- Q^T K Q on a basis Q (M, 3, m), for the warm starts' reduced model
  (:mod:`fpm.dynamics.predictor`);
- the gradient's derivatives by each spring's k and each cell's kappa against a field w
  (:meth:`SpringSystem.sensitivity`), for adjoint gradients (:mod:`fpm.fitting.adjoint`).

The loops over springs are compiled (numba: :func:`_spring_forces` and friends). A system
depends only on the problem and its free nodes and is read only: :func:`shared_system` and
:func:`spring_lists` build a problem's systems and perturbed lists once and share them between
its solvers (one per thread), which keep their own tangent buffers, hierarchies and warm starts.
"""

from __future__ import annotations

import threading
import weakref
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numba import njit

from ..model.forces import Stiffness, cells
from ..model.perturbed_list import Adjacency, PerturbedListCache
from ..model.problem import Problem
from ..model.stiffness import has_volume
from ..model.volume import Cells
from .cell_terms import (
    _cell_energy_change,
    _cell_forces,
    _cell_reduced_tangent,
    _cell_sensitivity,
    _cell_tangent_blocks,
)

_SHARED_SYSTEMS = threading.Lock()
"""Guards the problem's shared lists and spring systems while one is looked up or built."""


class Params(NamedTuple):
    """The stiffness of one system's active terms: ``springs`` (A,) N/m, ``kappa`` (C,) Pa or
    None (no volume term), and both as one ``flat`` vector (what warm starts compare)."""

    springs: np.ndarray
    kappa: np.ndarray | None
    flat: np.ndarray


class SpringSystem:
    """The force terms of one perturbed list (springs, and cells when the model has the volume
    term), as functions of the free nodes' displacements.

    Free nodes are the list's nodes in ascending index order (``free``); a displacement field
    is an (M, 3) array over them (node-major unknowns u0, v0, w0, u1, ... in the matrices).
    Only springs with at least one free end take part ("active" springs), and only cells with
    at least one free corner; held nodes stay at rest. The loops over springs and cells are
    compiled (:func:`_spring_forces`, :func:`fpm.dynamics.cell_terms._cell_forces` and
    friends); the tangent's block pattern is built once, vectorised.

    Attributes:
        free: (M,) int64 free node indices, ascending.
        springs: (A,) int64 indices of the active springs (rows of ``problem.solid.springs``).
        ends: (A, 2) int64 local indices of each active spring's ends (-1: a held node).
        rest_length: (A,) their rest lengths, m.
        rest_vector: (A, 3) x_j - x_i at rest, m.
        cells: the active cells (:class:`fpm.model.volume.Cells`), or None without a volume term.
        cell_ids: (C,) their indices among the solid's hexahedra.
        cell_ends: (C, 8) local indices of their corners (-1: a held node).
    """

    def __init__(self, problem: Problem, free: np.ndarray):
        self.free = np.sort(np.asarray(free, dtype=np.int64))
        m = len(self.free)
        local = np.full(problem.n_nodes, -1, dtype=np.int64)
        local[self.free] = np.arange(m)
        pairs = problem.solid.springs
        ends = local[pairs]
        self.springs = np.flatnonzero((ends >= 0).any(axis=1))
        self.ends = np.ascontiguousarray(ends[self.springs])
        self.rest_length = problem.rest_lengths[self.springs]
        nodes = problem.nodes
        self.rest_vector = nodes[pairs[self.springs, 1]] - nodes[pairs[self.springs, 0]]
        self.cells: Cells | None = None
        self.cell_ids = np.zeros(0, dtype=np.int64)
        self.cell_ends = np.zeros((0, 8), dtype=np.int64)
        if has_volume(problem):
            every = cells(problem)
            corner_ends = local[every.corners]
            self.cell_ids = np.flatnonzero((corner_ends >= 0).any(axis=1))
            self.cells = every.subset(self.cell_ids)
            self.cell_ends = np.ascontiguousarray(corner_ends[self.cell_ids])
        self._tangent_pattern()

    @property
    def n_free(self) -> int:
        return len(self.free)

    def parameters(self, stiffness: Stiffness) -> Params:
        """The active terms' stiffness from the model's :class:`~fpm.model.forces.Stiffness`."""
        k = np.ascontiguousarray(stiffness.springs[self.springs])
        if self.cells is None:
            return Params(k, None, k)
        if stiffness.volume is None:
            raise ValueError("this model has a volume term: give kappa (Stiffness.volume)")
        kappa = np.ascontiguousarray(stiffness.volume[self.cell_ids])
        return Params(k, kappa, np.concatenate([k, kappa]))

    def _tangent_pattern(self) -> None:
        """The tangent's block sparsity (BSR, 3x3 blocks, sorted) and, per active spring, the
        positions of its four blocks ii, jj, ij, ji in the block list (-1: not free); per
        active cell, the positions of its 8 x 8 corner blocks (-1: not both free)."""
        m = self.n_free
        li, lj = self.ends[:, 0], self.ends[:, 1]
        both = (li >= 0) & (lj >= 0)
        diag = np.arange(m)
        ca = np.repeat(self.cell_ends, 8, axis=1).ravel()  # (C*64,) corner a of each pair
        cb = np.tile(self.cell_ends, (1, 8)).ravel()  # corner b
        cell_pair = (ca >= 0) & (cb >= 0)
        rows = np.concatenate([diag, li[both], lj[both], ca[cell_pair]])
        cols = np.concatenate([diag, lj[both], li[both], cb[cell_pair]])
        keys, where = np.unique(rows * m + cols, return_inverse=True)
        self._indices = (keys % m).astype(np.int32)
        self._indptr = np.zeros(m + 1, dtype=np.int32)
        np.cumsum(np.bincount(keys // m, minlength=m), out=self._indptr[1:])
        self._n_blocks = len(keys)
        self._diagonal_block = where[:m]
        index = np.int32 if len(keys) < 2**31 else np.int64  # half the memory of int64
        position = np.full((len(li), 4), -1, dtype=index)
        position[li >= 0, 0] = where[li[li >= 0]]
        position[lj >= 0, 1] = where[lj[lj >= 0]]
        nb = int(both.sum())
        position[both, 2] = where[m : m + nb]
        position[both, 3] = where[m + nb : m + 2 * nb]
        self._position = position
        cell_position = np.full(len(ca), -1, dtype=index)
        cell_position[cell_pair] = where[m + 2 * nb :]
        self._cell_position = cell_position.reshape(-1, 8, 8)

    def blocks(self) -> np.ndarray:
        """(B, 3, 3) zeros: the values of a tangent on this system's block pattern."""
        return np.zeros((self._n_blocks, 3, 3))

    def stretch(self, u: np.ndarray) -> np.ndarray:
        """(A,) spring elongations |r| - L at displacements u (M, 3), m."""
        padded = np.vstack([u, np.zeros((1, 3))])  # row -1: a held end does not move
        r = self.rest_vector + padded[self.ends[:, 1]] - padded[self.ends[:, 0]]
        return np.sqrt(np.einsum("ij,ij->i", r, r)) - self.rest_length

    def energy(self, u: np.ndarray, k: Params, forces: np.ndarray) -> float:
        """E(u), J: the terms' energy minus the forces' work. u (M, 3) m, forces (M, 3) N."""
        return float(self._internal(u, k, np.empty_like(u)) - np.einsum("ij,ij->", forces, u))

    def gradient(self, u: np.ndarray, k: Params, forces: np.ndarray) -> np.ndarray:
        """dE/du (M, 3), N: minus the unbalanced nodal force F_i + F_s of each free node."""
        grad = np.empty_like(u)
        self._internal(u, k, grad)
        grad -= forces
        return grad

    def _internal(self, u: np.ndarray, k: Params, grad: np.ndarray) -> float:
        """The terms' energy, J; fills ``grad`` (M, 3) with its gradient, N."""
        energy = _spring_forces(self.rest_vector, self.ends, self.rest_length, k.springs, u, grad)
        if self.cells is not None and k.kappa is not None:
            c = self.cells
            energy += _cell_forces(c.rest, c.volume, self.cell_ends, k.kappa, u, grad)
        return energy

    def energy_change(
        self, u: np.ndarray, step: np.ndarray, k: Params, forces: np.ndarray
    ) -> float:
        """E(u + step) - E(u), J, without the cancellation of subtracting two energies.

        Per spring, (l' - L)^2 - (l - L)^2 = (l' - l)(l' + l - 2L) with
        l' - l = (2 r.dr + |dr|^2) / (l' + l); per cell likewise with the volume change
        (:func:`fpm.model.volume.volume_change`).
        """
        change = _energy_change(self.rest_vector, self.ends, self.rest_length, k.springs, u, step)
        if self.cells is not None and k.kappa is not None:
            c = self.cells
            change += _cell_energy_change(c.rest, c.volume, self.cell_ends, k.kappa, u, step)
        return float(change - np.einsum("ij,ij->", forces, step))

    def tangent(
        self,
        u: np.ndarray,
        k: Params,
        *,
        modified: bool = True,
        shift: float = 0.0,
        out: np.ndarray | None = None,
    ) -> sp.bsr_matrix:
        """Hessian of E at u, (3M, 3M) N/m in 3x3 node blocks.

        Per spring k [n n^T + c (I - n n^T)], c = 1 - L/|r|; per cell
        (kappa / V0) g g^T + p d^2V/dx^2 (g = dV/dx, p = kappa (V - V0) / V0). ``modified``
        clamps c at 0 and drops the cells' p term (a positive semi-definite tangent; exact
        wherever no spring is compressed and no cell has changed volume). ``shift`` adds
        shift * (largest diagonal entry) to the diagonal. ``out``: a (B, 3, 3) buffer
        (:meth:`blocks`) to fill rather than new memory (the matrix is then valid until the
        buffer's next use).
        """
        if out is not None:
            data = out
            data.fill(0.0)
        else:
            data = self.blocks()
        _tangent_blocks(
            self.rest_vector, self.ends, self.rest_length, k.springs, u, modified, self._position,
            data,
        )  # fmt: skip
        if self.cells is not None and k.kappa is not None:
            c = self.cells
            _cell_tangent_blocks(
                c.rest, c.volume, self.cell_ends, k.kappa, u, modified, self._cell_position, data
            )
        if shift:
            diagonal = data[self._diagonal_block]
            top = float(np.einsum("nii->ni", diagonal).max(initial=0.0))
            diagonal[:, [0, 1, 2], [0, 1, 2]] += shift * top
            data[self._diagonal_block] = diagonal
        m = self.n_free
        return sp.bsr_matrix((data, self._indices, self._indptr), shape=(3 * m, 3 * m))

    def sensitivity(self, u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How the gradient dE/du at u (M, 3) moves with each term's stiffness, against the
        field w (M, 3): per active spring w . d(dE/du)/dk_s = (|r_s| - L_s) n_s . (w_j - w_i),
        m, and per active cell w . d(dE/du)/dkappa_c = (V_c - V0_c) / V0_c sum_n g_n . w_n,
        m^3 / Pa (held nodes: w = 0). With w the adjoint of a cost J, minus these are dJ/dk_s
        and dJ/dkappa_c (:mod:`fpm.fitting.adjoint`). Returns ((A,), (C,); empty without cells)."""
        zero = np.zeros((1, 3))
        padded_u, padded_w = np.vstack([u, zero]), np.vstack([w, zero])
        i, j = self.ends[:, 0], self.ends[:, 1]
        r = self.rest_vector + padded_u[j] - padded_u[i]
        length = np.sqrt(np.einsum("ij,ij->i", r, r))
        moved = np.einsum("ij,ij->i", r, padded_w[j] - padded_w[i]) / length
        springs = (length - self.rest_length) * moved
        cells = np.zeros(len(self.cell_ids))
        if self.cells is not None:
            c = self.cells
            _cell_sensitivity(c.rest, c.volume, self.cell_ends, u, w, cells)
        return springs, cells

    def reduced_tangent(self, u: np.ndarray, k: Params, basis: np.ndarray, modified: bool):
        """(m, m) Q^T K Q for the basis Q (M, 3, m) at u; the cells contribute their
        modified part (kappa / V0) (Q^T g)(Q^T g)^T only (a warm start's chord steps need no
        more; every answer is checked against the full residual)."""
        m = basis.shape[2]
        out = np.empty((m, m))
        _reduced_tangent(
            self.rest_vector, self.ends, self.rest_length, k.springs, u, basis, modified, out
        )
        if self.cells is not None and k.kappa is not None:
            c = self.cells
            _cell_reduced_tangent(c.rest, c.volume, self.cell_ends, k.kappa, u, basis, out)
        return out


@njit(cache=True, nogil=True)
def _spring_forces(
    rest_vector: np.ndarray,
    ends: np.ndarray,
    rest_length: np.ndarray,
    k: np.ndarray,
    u: np.ndarray,
    grad: np.ndarray,
) -> float:
    """Fill ``grad`` (M, 3) with the springs' dE/du, N; return their energy, J."""
    grad[:] = 0.0
    energy = 0.0
    for s in range(len(rest_length)):
        i, j = ends[s, 0], ends[s, 1]
        r0, r1, r2 = rest_vector[s, 0], rest_vector[s, 1], rest_vector[s, 2]
        if i >= 0:
            r0, r1, r2 = r0 - u[i, 0], r1 - u[i, 1], r2 - u[i, 2]
        if j >= 0:
            r0, r1, r2 = r0 + u[j, 0], r1 + u[j, 1], r2 + u[j, 2]
        length = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        stretch = length - rest_length[s]
        energy += 0.5 * k[s] * stretch * stretch
        t = k[s] * stretch / max(length, 1e-300)
        if i >= 0:
            grad[i, 0] -= t * r0
            grad[i, 1] -= t * r1
            grad[i, 2] -= t * r2
        if j >= 0:
            grad[j, 0] += t * r0
            grad[j, 1] += t * r1
            grad[j, 2] += t * r2
    return energy


@njit(cache=True, nogil=True)
def _energy_change(
    rest_vector: np.ndarray,
    ends: np.ndarray,
    rest_length: np.ndarray,
    k: np.ndarray,
    u: np.ndarray,
    step: np.ndarray,
) -> float:
    """The springs' energy at u + step minus at u, J (see :meth:`SpringSystem.energy_change`)."""
    total = 0.0
    for s in range(len(rest_length)):
        i, j = ends[s, 0], ends[s, 1]
        r0, r1, r2 = rest_vector[s, 0], rest_vector[s, 1], rest_vector[s, 2]
        d0 = d1 = d2 = 0.0
        if i >= 0:
            r0, r1, r2 = r0 - u[i, 0], r1 - u[i, 1], r2 - u[i, 2]
            d0, d1, d2 = -step[i, 0], -step[i, 1], -step[i, 2]
        if j >= 0:
            r0, r1, r2 = r0 + u[j, 0], r1 + u[j, 1], r2 + u[j, 2]
            d0, d1, d2 = d0 + step[j, 0], d1 + step[j, 1], d2 + step[j, 2]
        length = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        q0, q1, q2 = r0 + d0, r1 + d1, r2 + d2
        both = length + np.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
        if both > 0.0:
            grow = (2.0 * (r0 * d0 + r1 * d1 + r2 * d2) + d0 * d0 + d1 * d1 + d2 * d2) / both
            total += 0.5 * k[s] * grow * (both - 2.0 * rest_length[s])
    return total


@njit(cache=True, nogil=True, inline="always")
def _spring_tangent(
    rest_vector: np.ndarray,
    ends: np.ndarray,
    rest_length: np.ndarray,
    k: np.ndarray,
    u: np.ndarray,
    s: int,
    modified: bool,
) -> tuple[float, float, float, float, float]:
    """Spring ``s`` at u: its unit direction n (3 floats) and the weights a = k (1 - c),
    b = k c of its tangent block a n n^T + b I, c = 1 - L/|r| (clamped at 0 if ``modified``)."""
    i, j = ends[s, 0], ends[s, 1]
    r0, r1, r2 = rest_vector[s, 0], rest_vector[s, 1], rest_vector[s, 2]
    if i >= 0:
        r0, r1, r2 = r0 - u[i, 0], r1 - u[i, 1], r2 - u[i, 2]
    if j >= 0:
        r0, r1, r2 = r0 + u[j, 0], r1 + u[j, 1], r2 + u[j, 2]
    length = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-300)
    c = 1.0 - rest_length[s] / length
    if modified and c < 0.0:
        c = 0.0
    return r0 / length, r1 / length, r2 / length, k[s] * (1.0 - c), k[s] * c


@njit(cache=True, nogil=True)
def _tangent_blocks(
    rest_vector: np.ndarray,
    ends: np.ndarray,
    rest_length: np.ndarray,
    k: np.ndarray,
    u: np.ndarray,
    modified: bool,
    position: np.ndarray,
    data: np.ndarray,
) -> None:
    """Add each spring's 3x3 block k [(1 - c) n n^T + c I] into ``data`` (blocks, 3, 3): +
    on its diagonal blocks (``position`` columns 0, 1), - on its off-diagonal ones (2, 3)."""
    block = np.empty((3, 3))
    for s in range(len(rest_length)):
        n0, n1, n2, a, b = _spring_tangent(rest_vector, ends, rest_length, k, u, s, modified)
        block[0, 0] = a * n0 * n0 + b
        block[1, 1] = a * n1 * n1 + b
        block[2, 2] = a * n2 * n2 + b
        block[0, 1] = block[1, 0] = a * n0 * n1
        block[0, 2] = block[2, 0] = a * n0 * n2
        block[1, 2] = block[2, 1] = a * n1 * n2
        for corner in range(4):
            at = position[s, corner]
            if at >= 0:
                sign = 1.0 if corner < 2 else -1.0
                for p in range(3):
                    for q in range(3):
                        data[at, p, q] += sign * block[p, q]


@njit(cache=True, nogil=True)
def _reduced_tangent(
    rest_vector: np.ndarray,
    ends: np.ndarray,
    rest_length: np.ndarray,
    k: np.ndarray,
    u: np.ndarray,
    basis: np.ndarray,
    modified: bool,
    out: np.ndarray,
) -> None:
    """Fill ``out`` (m, m) with Q^T K Q for the basis Q (M, 3, m) and the tangent K at u (M, 3)
    (``modified``: clamped): per spring, k (1 - c) (D^T n)(D^T n)^T + k c D^T D with
    D = Q_j - Q_i (3, m)."""
    m = basis.shape[2]
    out[:] = 0.0
    d = np.zeros((3, m))
    dn = np.zeros(m)
    for s in range(len(rest_length)):
        i, j = ends[s, 0], ends[s, 1]
        n0, n1, n2, a, b = _spring_tangent(rest_vector, ends, rest_length, k, u, s, modified)
        for x in range(3):
            for p in range(m):
                value = 0.0
                if j >= 0:
                    value += basis[j, x, p]
                if i >= 0:
                    value -= basis[i, x, p]
                d[x, p] = value
        for p in range(m):
            dn[p] = d[0, p] * n0 + d[1, p] * n1 + d[2, p] * n2
        for p in range(m):
            ap = a * dn[p]
            for q in range(p, m):
                dd = d[0, p] * d[0, q] + d[1, p] * d[1, q] + d[2, p] * d[2, q]
                out[p, q] += ap * dn[q] + b * dd
    for p in range(m):
        for q in range(p):
            out[p, q] = out[q, p]


def spring_lists(problem: Problem) -> PerturbedListCache:
    """The problem's perturbed lists over its springs' adjacency (no stiffness factors: the
    static solvers pass every spring's stiffness), built once and shared by its static solvers
    (two threads asking for a new list at once may both build it, the same list)."""
    with _SHARED_SYSTEMS:
        found = problem.cache.spring_lists
        if found is None:
            solid = problem.solid
            adjacency = Adjacency.from_springs(
                len(solid.nodes), solid.springs, problem.rest_lengths, None
            )
            found = problem.cache.spring_lists = PerturbedListCache(adjacency, problem.fixed)
        return found


def shared_system(problem: Problem, free: np.ndarray) -> SpringSystem:
    """The problem's :class:`SpringSystem` on the free nodes ``free`` (ascending), built once
    and shared by every solver of the problem that holds it (a system is read only: each
    solver keeps its own tangent buffer, hierarchy and warm starts). Kept in
    ``problem.cache.spring_systems`` by weak reference, so it lives as long as some solver
    keeps it: the chains running at once on threads hold one copy instead of one each."""
    key = free.tobytes()
    with _SHARED_SYSTEMS:
        systems = problem.cache.spring_systems
        if systems is None:
            systems = problem.cache.spring_systems = weakref.WeakValueDictionary()
        system = systems.get(key)
        if system is None:
            system = systems[key] = SpringSystem(problem, free)
        return system
