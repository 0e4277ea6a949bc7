"""The static equilibrium of the FPM: the state a settled dynamic run reaches, found directly.

A settled run's state does not depend on the damping d (physics.md, Round 2): it is the
minimum, over the displacements u_i of the perturbed-list nodes, of the springs' energy minus
the work of the constant nodal forces,

    E(u) = sum_s 1/2 k_s (|r_s| - L_s)^2 - sum_i F_i . u_i,     r_s = x_j - x_i,  x = X + u,

nodes outside the list and fixed nodes held at their rest positions X; F_i the load case's
nodal forces plus the node weight m_i g when the spec's gravity is non-zero. The springs are
geometrically nonlinear (they rotate and stretch), so E is minimised by Newton's method:

- gradient: dE/dx_j = k (|r| - L) n = -dE/dx_i (n = r / |r|); the unbalanced nodal force
  F_i + F_s of the dynamic run (:mod:`fpm.dynamics.voigt`) is minus the gradient;
- tangent of one spring (3x3, [[K, -K], [-K, K]] on its two nodes):
  K = k [n n^T + (1 - L/|r|) (I - n n^T)], indefinite where the spring is compressed. Each
  Newton step tries the exact tangent first (quadratic convergence: a press compresses springs,
  and clamping them cost 2-3 times the iterations); where it is not positive definite (CG meets
  negative curvature, or the step does not descend) the step is redone with the factor
  (1 - L/|r|) clamped at 0, a positive semi-definite tangent whose steps always descend; where
  that is singular (a mechanism), with a small diagonal shift. A backtracking (Armijo) line
  search on E makes every step decrease it (energy changes are computed without cancellation:
  :meth:`SpringSystem.energy_change`). The loops over springs are compiled (numba);
- linear solves: sparse LU below :data:`AMG_FROM_UNKNOWNS` unknowns; above, conjugate gradients
  preconditioned by a smoothed-aggregation multigrid hierarchy (the FEM's hierarchy, V-cycle
  and CG, from :mod:`fpm.fem.linear_solver`) built on one tangent and kept across Newton steps,
  stiffness changes, load cases and calls for as long as CG converges at the rate it had when
  the hierarchy was new; inexact Newton: CG stops at a residual relative to the current one
  (Eisenstat-Walker, choice 2), or once every node's linear residual is below half the target;
- warm starts (:class:`_Predictor`): converged solutions are kept per (load case, depth). With
  one k, u(c k, F) = u(k, F / c) exactly, so solutions at proportional stiffnesses are
  interpolated along the load factor; otherwise the nearest is rescaled; then E is minimised
  over the span of the nearest few (a Galerkin reduced model). On an annealing walk with one k
  most solves then need no Newton step at all.

Converged when the largest unbalanced nodal force over the list is at most ``tolerance`` times
the largest applied nodal force (the settle criterion of the dynamic run, with a tenth of its
tolerance by default, so the static answer is at least as converged as a settled run).

Thread-safety: a :class:`StaticSolver` keeps mutable caches (warm starts, multigrid
hierarchies, its tangent buffers) and is not thread-safe; use one per thread.
:func:`static_equilibrium` does so: it keeps one solver per thread on the problem. What only
depends on the problem, its perturbed lists and spring systems, is read only and shared by its
solvers (:func:`spring_lists`, :func:`shared_system`).
"""

from __future__ import annotations

import math
import threading
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numba import njit

from ..fem.linear_solver import (
    NegativeCurvature,
    ReusedHierarchy,
    SingularStiffnessError,
    amg_hierarchy,
    conjugate_gradients,
    dot,
    factorize,
    rigid_body_modes,
)
from ..model.forces import Stiffness, cells
from ..model.perturbed_list import Adjacency, PerturbedListCache
from ..model.problem import Problem
from ..model.stiffness import has_volume, model_stiffness
from ..model.volume import (
    COEFFICIENTS,
    Cells,
    coefficient_gradient,
    coefficient_hessian,
    corner_gradient,
    volume_change,
)

AMG_FROM_UNKNOWNS = 300
"""Free unknowns from which the Newton steps use multigrid-preconditioned CG instead of LU.
Measured on `full` lattices (first solve, hierarchy built in it): 300 unknowns 5.6 ms with CG
against 8.7 ms with LU, 2,700 unknowns 25 ms against 220 ms (SuperLU's fill-in on the 27-point
stencil grows fast); below ~150 unknowns LU is as fast and copes with singular tangents."""

MAX_ITERATIONS = 100
"""Newton iterations before a solve gives up (a cold solve of the paper's cube at 1 N needs 4,
of the organ at 20k nodes 3-4; a warm one 0-2)."""

MAX_CG_ITERATIONS = 300
"""CG iterations per Newton step; a step that needs more uses what CG reached (still a descent
direction) and the hierarchy is rebuilt for the next."""

ETA_MAX = 0.1
"""Largest relative CG tolerance of an inexact Newton step (Eisenstat-Walker's eta)."""

NEAR = 1e3
"""Within this factor of the target residual, a Newton step's CG runs to the target (the
quadratic term is negligible there, so one accurate step beats two loose ones)."""

ARMIJO = 1e-4
"""Sufficient-decrease constant of the line search: accept E(u + a p) - E(u) <= ARMIJO a g.p."""

SNAPSHOTS = 12
"""Converged solutions kept per (load case, depth) for warm starts."""

LAGRANGE_POINTS = 4
"""Solutions at proportional stiffnesses interpolated along the load factor (with s = 0)."""

SAMPLE = 4096
"""Springs (evenly spread) on which a warm start compares stiffnesses."""

GALERKIN_SIZE = 8
"""Nearest solutions spanning the reduced model a warm start is refined on."""

GALERKIN_ITERATIONS = 4
"""Chord-Newton steps on the reduced model (:func:`_galerkin`)."""

DIVERGED = 10.0
"""A Newton iterate that moves a node this many times the solid's size away has diverged. An
equilibrium further than the size itself is reported as not converged (a dynamic run stops
there as diverged)."""

SHIFT = 1e-8
"""Diagonal shift, relative to the largest diagonal entry, of the last-resort tangent (a
singular one: a mechanism)."""

_MULTIGRID_SETUP = threading.Lock()
"""One multigrid setup at a time in a process: the solvers of chains running at once on threads
would otherwise hold two setups' transients together (a tangent and smoothed aggregation's
intermediates, about 0.5 GB each on the 93,705-node organ), the peak of the calibration."""

_SHARED_SYSTEMS = threading.Lock()
"""Guards the problem's shared lists and spring systems while one is looked up or built."""

MAX_SYSTEMS = 6
"""Spring systems (distinct perturbed lists) a solver keeps, with their multigrid hierarchies
and warm starts: at 20k nodes one full-depth system with its hierarchy takes ~150 MB."""


class EquilibriumError(RuntimeError):
    """A static solve that did not converge (raised by :meth:`Equilibrium.check`)."""


@dataclass
class Equilibrium:
    """The static equilibrium of one load case.

    Attributes:
        displacements: (N, 3) nodal displacements, m (zero outside the perturbed list).
        iterations: Newton iterations taken.
        linear_iterations: CG iterations over all Newton steps (0 when solved by LU).
        residual: largest unbalanced nodal force |F_i + F_s| over the list nodes, N.
        converged: residual <= tolerance * largest applied nodal force (and no node moved
            further than the solid's size, where a dynamic run would stop as diverged).
        perturbed: number of nodes in the perturbed list (the free nodes).
        depth: layers the list reached (<= the depth asked for).
        load_case: index of the load case.
        tolerance: the relative tolerance solved to.
        message: why the solve stopped, when it did not converge ("" otherwise).
        start: where Newton started: "rest", or "predicted" from earlier solutions.
        seconds: wall time of the solve, s.
    """

    displacements: np.ndarray
    iterations: int
    linear_iterations: int
    residual: float
    converged: bool
    perturbed: int
    depth: int
    load_case: int
    tolerance: float = 0.0
    message: str = ""
    start: str = "rest"
    seconds: float = 0.0

    def check(self) -> Equilibrium:
        """Return self if converged, else raise :class:`EquilibriumError` with the message."""
        if not self.converged:
            raise EquilibriumError(self.message or "static equilibrium did not converge")
        return self


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
    compiled (:func:`_spring_forces`, :func:`_cell_forces` and friends); the tangent's block
    pattern is built once, vectorised.

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
        buffer's next use; at 20k nodes 34 MB, whose first touch costs more than the assembly).
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


@njit(cache=True, nogil=True, inline="always")
def _cell_state(
    rest: np.ndarray, ends: np.ndarray, u: np.ndarray, c: int, a: np.ndarray, da: np.ndarray
) -> None:
    """a1..a6 of cell ``c`` at displacements u (``a`` (6, 3)) and their change from rest
    (``da``); held corners (-1) do not move."""
    for k in range(6):
        for d in range(3):
            value = 0.0
            for n in range(8):
                i = ends[c, n]
                if i >= 0:
                    value += COEFFICIENTS[k, n] * u[i, d]
            da[k, d] = value
            a[k, d] = rest[c, k, d] + value


@njit(cache=True, nogil=True)
def _cell_forces(
    rest: np.ndarray,
    volume: np.ndarray,
    ends: np.ndarray,
    kappa: np.ndarray,
    u: np.ndarray,
    grad: np.ndarray,
) -> float:
    """Add the cells' dE/du to ``grad`` (M, 3), N; return their energy, J."""
    a, da = np.empty((6, 3)), np.empty((6, 3))
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    energy = 0.0
    for c in range(len(volume)):
        _cell_state(rest, ends, u, c, a, da)
        change = volume_change(rest[c], da)
        energy += 0.5 * kappa[c] * change * change / volume[c]
        pressure = kappa[c] * change / volume[c]
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        for n in range(8):
            i = ends[c, n]
            if i >= 0:
                for d in range(3):
                    grad[i, d] += pressure * grad_x[n, d]
    return energy


@njit(cache=True, nogil=True)
def _cell_energy_change(
    rest: np.ndarray,
    volume: np.ndarray,
    ends: np.ndarray,
    kappa: np.ndarray,
    u: np.ndarray,
    step: np.ndarray,
) -> float:
    """The cells' energy at u + step minus at u, J: per cell
    1/2 kappa / V0 (dV' - dV)(dV' + dV), dV' - dV = V(a + ds) - V(a) without cancellation."""
    a, da = np.empty((6, 3)), np.empty((6, 3))
    ds, dummy = np.empty((6, 3)), np.empty((6, 3))
    total = 0.0
    for c in range(len(volume)):
        _cell_state(rest, ends, u, c, a, da)
        _cell_state(rest, ends, step, c, dummy, ds)
        change = volume_change(rest[c], da)
        more = volume_change(a, ds)
        total += 0.5 * kappa[c] / volume[c] * more * (2.0 * change + more)
    return total


@njit(cache=True, nogil=True)
def _cell_tangent_blocks(
    rest: np.ndarray,
    volume: np.ndarray,
    ends: np.ndarray,
    kappa: np.ndarray,
    u: np.ndarray,
    modified: bool,
    position: np.ndarray,
    data: np.ndarray,
) -> None:
    """Add each cell's blocks (kappa / V0) g_n g_m^T + p H_nm (p term unless ``modified``) into
    ``data`` at ``position`` (C, 8, 8)."""
    a, da = np.empty((6, 3)), np.empty((6, 3))
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    hessian_a = np.empty((6, 6, 3, 3))
    half = np.empty((6, 8, 3, 3))  # sum_q H_a[k, q] C_qm
    hessian_x = np.empty((8, 8, 3, 3))  # sum_k C_kn half[k, m]
    for c in range(len(volume)):
        _cell_state(rest, ends, u, c, a, da)
        weight = kappa[c] / volume[c]
        pressure = weight * volume_change(rest[c], da)
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        if not modified:
            coefficient_hessian(a, hessian_a)
            half[:] = 0.0
            for k in range(6):
                for q in range(6):
                    for m in range(8):
                        cq = COEFFICIENTS[q, m]
                        for x in range(3):
                            for y in range(3):
                                half[k, m, x, y] += hessian_a[k, q, x, y] * cq
            hessian_x[:] = 0.0
            for k in range(6):
                for n in range(8):
                    ck = COEFFICIENTS[k, n]
                    for m in range(8):
                        for x in range(3):
                            for y in range(3):
                                hessian_x[n, m, x, y] += ck * half[k, m, x, y]
        for n in range(8):
            for m in range(8):
                at = position[c, n, m]
                if at < 0:
                    continue
                for x in range(3):
                    for y in range(3):
                        value = weight * grad_x[n, x] * grad_x[m, y]
                        if not modified:
                            value += pressure * hessian_x[n, m, x, y]
                        data[at, x, y] += value


@njit(cache=True, nogil=True)
def _cell_reduced_tangent(
    rest: np.ndarray,
    volume: np.ndarray,
    ends: np.ndarray,
    kappa: np.ndarray,
    u: np.ndarray,
    basis: np.ndarray,
    out: np.ndarray,
) -> None:
    """Add sum_c (kappa_c / V0_c) w w^T to ``out`` (m, m), w = sum_n Q_n^T g_n (m,)."""
    m = basis.shape[2]
    a, da = np.empty((6, 3)), np.empty((6, 3))
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    w = np.empty(m)
    for c in range(len(volume)):
        _cell_state(rest, ends, u, c, a, da)
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        w[:] = 0.0
        for n in range(8):
            i = ends[c, n]
            if i >= 0:
                for p in range(m):
                    w[p] += (
                        grad_x[n, 0] * basis[i, 0, p]
                        + grad_x[n, 1] * basis[i, 1, p]
                        + grad_x[n, 2] * basis[i, 2, p]
                    )
        weight = kappa[c] / volume[c]
        for p in range(m):
            for q in range(m):
                out[p, q] += weight * w[p] * w[q]


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


@dataclass
class _Snapshot:
    """A converged solution: free displacements u (M, 3), m, and its active springs'
    stiffness at the :data:`SAMPLE` of springs, N/m (the whole (A,) array would cost more
    memory than u)."""

    u: np.ndarray
    k_sample: np.ndarray


class _Predictor:
    """Starting points for one (load case, depth) from its earlier solutions (warm starts).

    Let k be the new stiffness and u_j an earlier solution found at stiffness c_j k
    (proportional, as when one k changes). The equilibrium equations are homogeneous in
    (k, F), so u_j = u(k, F / c_j): u_j is the point s_j = 1 / c_j of the curve
    w(s) = u(k, s F), which also passes through w(0) = 0, and the answer is w(1). So solutions
    at proportional stiffnesses are interpolated along s (Lagrange, through 0 and the nearest
    few); with a single one that is the rescaling c_j u_j, exact for the linear part. Otherwise
    (family stiffnesses changed unevenly) the nearest solution, rescaled by its mean stiffness
    ratio. Then, with two or more solutions kept, E is minimised over their span (a Galerkin
    reduced model, :func:`_galerkin`), which captures how the answer varies with the stiffness
    from the solutions already found.

    Stiffnesses are compared on a fixed sample of springs (:data:`SAMPLE`): a mismatch outside
    it only makes a start worse, never an answer wrong (every answer is checked against the
    residual).
    """

    def __init__(self, n_springs: int) -> None:
        self.snapshots: list[_Snapshot] = []
        self.sample = slice(None, None, max(1, n_springs // SAMPLE))

    def add(self, u: np.ndarray, k: np.ndarray) -> None:
        """Keep a converged solution (replacing one at the same stiffness; oldest out)."""
        sample = k[self.sample].copy()
        self.snapshots = [s for s in self.snapshots if not np.array_equal(s.k_sample, sample)]
        self.snapshots.append(_Snapshot(u.copy(), sample))
        del self.snapshots[:-SNAPSHOTS]

    def relation(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per snapshot: log c_j (its stiffness over k, geometric mean over the sample) and
        the spread of the log ratio about it (0: proportional)."""
        logs = np.log(np.stack([s.k_sample for s in self.snapshots])) - np.log(k[self.sample])
        scale = logs.mean(axis=1)
        spread = np.sqrt(((logs - scale[:, None]) ** 2).mean(axis=1))
        return scale, spread

    def predict(self, n_free: int, scale: np.ndarray, spread: np.ndarray) -> np.ndarray:
        """Starting displacements (M, 3) before the reduced-model refinement."""
        if not self.snapshots:
            return np.zeros((n_free, 3))
        proportional = np.flatnonzero(spread < 1e-12)
        if len(proportional):
            nearest: list[int] = []  # distinct nodes only (close ones make wild weights)
            for j in proportional[np.argsort(np.abs(scale[proportional]))]:
                if all(abs(scale[j] - scale[i]) > 1e-6 for i in nearest):
                    nearest.append(int(j))
            nearest = nearest[:LAGRANGE_POINTS]
            nodes = np.concatenate([[0.0], np.exp(-scale[nearest])])  # s_j = 1 / c_j
            u = np.zeros((n_free, 3))
            for a, j in enumerate(nearest, start=1):
                others = np.delete(nodes, a)
                u += float(np.prod((1.0 - others) / (nodes[a] - others))) * self.snapshots[j].u
            return u
        best = int(np.argmin(np.hypot(scale, spread)))
        return self.snapshots[best].u * math.exp(scale[best])

    def basis(self, scale: np.ndarray, spread: np.ndarray) -> np.ndarray | None:
        """(M, 3, m) orthonormal basis of the span of the nearest (<= GALERKIN_SIZE)
        solutions, or None with fewer than two."""
        if len(self.snapshots) < 2:
            return None
        columns: list[np.ndarray] = []
        for j in np.argsort(np.hypot(scale, spread))[:GALERKIN_SIZE]:
            v = self.snapshots[j].u.ravel().copy()  # modified Gram-Schmidt, twice (no BLAS)
            size = math.sqrt(dot(v, v))
            for _ in range(2):
                for q in columns:
                    v -= dot(q, v) * q
            left = math.sqrt(dot(v, v))
            if left > 1e-8 * size:
                columns.append(v / left)
        if len(columns) < 2:
            return None
        return np.stack(columns, axis=1).reshape(-1, 3, len(columns))


@dataclass
class _Stats:
    iterations: int = 0
    linear_iterations: int = 0
    reduced_iterations: int = 0
    message: str = ""
    start: str = "rest"


def spring_lists(problem: Problem) -> PerturbedListCache:
    """The problem's perturbed lists over its springs' adjacency (no stiffness factors: the
    static solvers pass every spring's stiffness), built once and shared by its static solvers
    (the adjacency of the 93,705-node organ is about 50 MB; two threads asking for a new list
    at once may both build it, the same list)."""
    with _SHARED_SYSTEMS:
        found = problem.cache.get("spring_lists")
        if found is None:
            solid = problem.solid
            adjacency = Adjacency.from_springs(
                len(solid.nodes), solid.springs, problem.rest_lengths, None
            )
            found = problem.cache["spring_lists"] = PerturbedListCache(adjacency, problem.fixed)
        return found


def shared_system(problem: Problem, free: np.ndarray) -> SpringSystem:
    """The problem's :class:`SpringSystem` on the free nodes ``free`` (ascending), built once
    and shared by every solver of the problem that holds it (a system is read only: each
    solver keeps its own tangent buffer, hierarchy and warm starts). Kept in ``problem.cache``
    by weak reference, so it lives as long as some solver keeps it: the chains running at once
    on threads hold one copy (on the 93,705-node organ about 0.2 GB) instead of one each."""
    key = free.tobytes()
    with _SHARED_SYSTEMS:
        systems = problem.cache.setdefault("spring_systems", weakref.WeakValueDictionary())
        system = systems.get(key)
        if system is None:
            system = systems[key] = SpringSystem(problem, free)
        return system


class StaticSolver:
    """Static equilibria of one problem's load cases, with everything worth keeping between
    calls: perturbed lists, spring systems, multigrid hierarchies and warm starts.

    Not thread-safe (warm starts and hierarchies are updated by every solve): use one per thread.
    ``hierarchies_built`` counts the multigrid hierarchies built so far.

    Args:
        problem: the problem.
        amg_from: free unknowns from which Newton steps use multigrid CG rather than LU
            (default :data:`AMG_FROM_UNKNOWNS`; 0 forces CG, a huge value forces LU).
        warm: start from earlier solutions of the same (load case, depth) (see
            :class:`_Predictor`); False = always from rest.
    """

    def __init__(self, problem: Problem, *, amg_from: int | None = None, warm: bool = True):
        self.problem = problem
        self.amg_from = AMG_FROM_UNKNOWNS if amg_from is None else int(amg_from)
        self.warm = warm
        solid = problem.solid
        self.lists = spring_lists(problem)
        gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
        self._weight = solid.masses[:, None] * gravity[None, :] if np.any(gravity) else None
        self._lists: dict[tuple[int, int | None], tuple[bytes, np.ndarray, int]] = {}
        self._systems: dict[bytes, SpringSystem] = {}
        self._buffers: dict[bytes, np.ndarray] = {}  # per system: the Newton tangent's values
        self._multigrid: dict[bytes, ReusedHierarchy] = {}
        self._predictors: dict[tuple[int, int | None], _Predictor] = {}
        self.hierarchies_built = 0

    def default_tolerance(self) -> float:
        """A tenth of the spec's settle_tolerance (1e-8 if that is 0)."""
        settle = self.problem.spec.fpm.settle_tolerance
        return settle / 10 if settle > 0 else 1e-8

    def system(self, load_case: int, depth: int | None) -> tuple[SpringSystem, int]:
        """The (cached) spring system of ``load_case``'s list at ``depth`` layers (None = all),
        and the layers that list reached.

        Lists with the same nodes share one system (and one multigrid hierarchy); the
        :data:`MAX_SYSTEMS` most recently used are kept, with their hierarchies and warm starts.
        """
        case = (load_case, depth)
        found = self._lists.get(case)
        if found is None:
            plist = self.lists.get(self.problem.load_cases[load_case].nodes, depth)
            free = np.sort(plist.order).astype(np.int64)
            found = self._lists[case] = (free.tobytes(), free, plist.layers)
        key, free, layers = found
        system = self._systems.pop(key, None)
        if system is None:
            system = shared_system(self.problem, free)
        self._systems[key] = system  # the most recently used last
        while len(self._systems) > MAX_SYSTEMS:
            oldest = next(iter(self._systems))
            del self._systems[oldest]
            self._buffers.pop(oldest, None)
            self._multigrid.pop(oldest, None)
            for other, (other_key, _, _) in list(self._lists.items()):
                if other_key == oldest:
                    self._predictors.pop(other, None)
        return system, layers

    def loads(self, load_case: int) -> np.ndarray:
        """(N, 3) constant nodal forces, N: the load case's plus the weight."""
        external = self.problem.load_cases[load_case].dense(self.problem.n_nodes)
        if self._weight is not None:
            external += self._weight
        return external

    def forces(self, load_case: int, system: SpringSystem) -> np.ndarray:
        """(M, 3) constant nodal forces on the free nodes, N (load case plus weight)."""
        return self.loads(load_case)[system.free]

    def forget(self, *, multigrid: bool = True) -> None:
        """Drop the warm starts (the next solves start from rest) and, unless ``multigrid`` is
        False, the multigrid hierarchies."""
        self._predictors.clear()
        if multigrid:
            self._multigrid.clear()

    def solve(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        *,
        tolerance: float | None = None,
    ) -> Equilibrium:
        """The static equilibrium of ``load_case``.

        Args:
            load_case: index into the problem's load cases.
            stiffness: the model's :class:`~fpm.model.forces.Stiffness`
                (:func:`fpm.model.stiffness.model_stiffness`), or (S,) stiffness of every
                spring, N/m, for a model without the volume term.
            depth: layers of the perturbed list; None = all reachable.
            tolerance: converged when the largest unbalanced nodal force is at most this times
                the largest applied nodal force; None = :meth:`default_tolerance`.
        """
        start = time.perf_counter()
        p = self.problem
        if not 0 <= load_case < len(p.load_cases):
            raise ValueError(f"load_case must be in 0..{len(p.load_cases) - 1}")
        stiffness = Stiffness.of(stiffness)
        if stiffness.springs.shape != (len(p.solid.springs),):
            raise ValueError(f"need one stiffness per spring, shape ({len(p.solid.springs)},)")
        if not np.all(stiffness.springs > 0):
            raise ValueError("need every spring stiffness > 0")
        if stiffness.volume is not None and not np.all(stiffness.volume >= 0):
            raise ValueError("need every volume stiffness >= 0")
        tol = self.default_tolerance() if tolerance is None else float(tolerance)
        if not tol > 0:
            raise ValueError("need tolerance > 0")
        system, layers = self.system(load_case, depth)
        forces = self.forces(load_case, system)
        k = system.parameters(stiffness)
        applied = float(np.sqrt(np.einsum("ij,ij->i", forces, forces)).max(initial=0.0))
        target = tol * applied
        stats = _Stats()
        predictor = self._predictors.get((load_case, depth))
        if predictor is None:
            predictor = self._predictors[(load_case, depth)] = _Predictor(len(k.flat))
        u, gradient = self._start(predictor, system, k, forces, applied, target, stats)
        u, residual, converged = self._newton(system, k, forces, u, gradient, target, stats)
        if converged and self.warm:
            predictor.add(u, k.flat)
        displacements = np.zeros_like(p.nodes)
        displacements[system.free] = u
        return Equilibrium(
            displacements=displacements,
            iterations=stats.iterations,
            linear_iterations=stats.linear_iterations,
            residual=residual,
            converged=converged,
            perturbed=system.n_free,
            depth=layers,
            load_case=load_case,
            tolerance=tol,
            message=stats.message,
            start=stats.start,
            seconds=time.perf_counter() - start,
        )

    def _start(
        self,
        predictor: _Predictor,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        applied: float,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Where Newton starts, and dE/du there: rest, or the predictor's guess refined on the
        reduced model."""
        rest = np.zeros((system.n_free, 3))
        if not self.warm or not predictor.snapshots or not len(k.flat):
            return rest, -forces
        scale, spread = predictor.relation(k.flat)
        u = predictor.predict(system.n_free, scale, spread)
        gradient = system.gradient(u, k, forces)
        if not _largest(gradient) < applied:  # worse than rest (the residual at rest: forces)
            return rest, -forces
        stats.start = "predicted"
        if _largest(gradient) > target:
            basis = predictor.basis(scale, spread)
            if basis is not None:
                u, gradient = _galerkin(system, k, forces, u, gradient, basis, target, stats)
        return u, gradient

    def _newton(
        self,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        u: np.ndarray,
        gradient: np.ndarray,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, float, bool]:
        """Newton with an Armijo line search on E from ``u`` (``gradient`` = dE/du there);
        returns (u, residual, converged)."""
        limit = self.problem.size
        residual = _largest(gradient)
        if residual <= target:
            return u, residual, self._within_size(u, stats)
        eta = ETA_MAX
        previous_norm: float | None = None
        for iteration in range(1, MAX_ITERATIONS + 1):
            stats.iterations = iteration
            norm = float(np.sqrt(np.einsum("ij,ij->", gradient, gradient)))
            if previous_norm is not None:  # Eisenstat-Walker choice 2, safeguarded
                ew = 0.9 * (norm / previous_norm) ** 2
                if 0.9 * eta * eta > 0.1:
                    ew = max(ew, 0.9 * eta * eta)
                eta = min(ETA_MAX, ew)
            if residual <= NEAR * target:  # close: the quadratic term is negligible
                eta = 0.0
            eta = max(eta, 0.5 * target / norm)  # no need to solve past the tolerance
            previous_norm = norm
            step, slope = self._newton_step(system, u, k, gradient, eta, 0.5 * target, stats)
            if step is None:
                stats.message = "the Newton step is not a descent direction (singular tangent?)"
                return u, residual, False
            alpha = 1.0
            for _ in range(40):
                change = system.energy_change(u, alpha * step, k, forces)
                if change <= ARMIJO * alpha * slope:
                    break
                # At round-off level (|slope| tiny against the forces' work) accept a step that
                # lowers the residual instead.
                work = abs(float(np.einsum("ij,ij->", forces, step)))
                if abs(slope) < 1e-11 * work:
                    trial = system.gradient(u + alpha * step, k, forces)
                    if _largest(trial) < residual:
                        break
                # Backtrack: minimiser of the quadratic through E(0), E'(0) and E(alpha).
                quad = -slope * alpha * alpha / (2.0 * (change - slope * alpha))
                alpha = min(max(quad, 0.1 * alpha), 0.5 * alpha) if np.isfinite(quad) else alpha / 2
            else:
                stats.message = f"line search failed at Newton iteration {iteration}"
                return u, residual, False
            u = u + alpha * step
            gradient = system.gradient(u, k, forces)
            residual = _largest(gradient)
            if not np.isfinite(residual) or not np.all(np.isfinite(u)):
                stats.message = "diverged: the state became non-finite"
                return u, float("inf"), False
            if _largest(u) > DIVERGED * limit:
                stats.message = f"diverged: a node moved {DIVERGED:g} x the solid's size away"
                return u, residual, False
            if residual <= target:
                return u, residual, self._within_size(u, stats)
        stats.message = (
            f"no convergence in {MAX_ITERATIONS} Newton iterations "
            f"(residual {residual:.3g} N, target {target:.3g} N)"
        )
        return u, residual, False

    def _within_size(self, u: np.ndarray, stats: _Stats) -> bool:
        """An equilibrium moving a node further than the solid's size is what a dynamic run
        stops at as diverged: not converged."""
        limit = self.problem.size
        if _largest(u) > limit:
            stats.message = (
                f"the equilibrium moves a node further than the solid's size, {limit:g} m"
            )
            return False
        return True

    def _newton_step(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        gradient: np.ndarray,
        eta: float,
        nodal_stop: float,
        stats: _Stats,
    ) -> tuple[np.ndarray | None, float]:
        """The Newton step (M, 3) and its slope gradient . step (< 0), or (None, nan).

        The exact tangent first (quadratic convergence near the solution); where it is not
        positive definite (compressed springs) the clamped one, whose steps always descend;
        where that is singular (a mechanism, e.g. an `axis` lattice at rest) the clamped one
        with a small diagonal shift (Levenberg-Marquardt).
        """
        key = system.free.tobytes()
        buffer = self._buffers.get(key)
        if buffer is None:
            buffer = self._buffers[key] = system.blocks()
        for modified, shift in ((False, 0.0), (True, 0.0), (True, SHIFT)):
            tangent = system.tangent(u, k, modified=modified, shift=shift, out=buffer)
            try:
                x = self._linear_solve(system, u, k, tangent, -gradient.ravel(), eta, nodal_stop)
            except NegativeCurvature as e:
                stats.linear_iterations += e.args[0]
                continue
            except SingularStiffnessError:
                continue
            stats.linear_iterations += x[1]
            step = x[0].reshape(-1, 3)
            slope = float(np.einsum("ij,ij->", gradient, step))
            if slope < 0:
                return step, slope
        return None, float("nan")

    def _linear_solve(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        tangent: sp.bsr_matrix,
        rhs: np.ndarray,
        eta: float,
        nodal_stop: float,
    ) -> tuple[np.ndarray, int]:
        """Solve tangent x = rhs: by LU (exactly) for small systems, else by CG preconditioned
        by the list's multigrid hierarchy (built on the clamped tangent at u when missing or
        stale) to the relative residual eta or the nodal residual ``nodal_stop``, N.
        Returns x and the CG iterations (0 for LU).

        Raises:
            NegativeCurvature: CG found ``tangent`` is not positive definite.
            SingularStiffnessError: LU found it singular.
        """
        if 3 * system.n_free < self.amg_from:
            return _direct_solve(tangent, rhs), 0
        mg = self._hierarchy(system, u, k)
        cg = conjugate_gradients(
            tangent,
            rhs,
            mg.precondition,
            rtol=eta,
            max_iterations=MAX_CG_ITERATIONS,
            nodal_stop=nodal_stop,
        )
        mg.record(cg.iterations, cg.residual, cg.converged)
        return cg.x, cg.iterations

    def _linear_hierarchy(
        self, system: SpringSystem, tangent: sp.sparray | sp.spmatrix
    ) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on ``tangent`` when there is none."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None:
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                blocks = sp.bsr_matrix(tangent, blocksize=(3, 3))
                mg = ReusedHierarchy(amg_hierarchy(blocks, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def _hierarchy(self, system: SpringSystem, u: np.ndarray, k: Params) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on the clamped tangent at u when missing or
        stale."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None or mg.stale:
            self._multigrid.pop(key, None)  # the stale one goes before the new one is built
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                reference = system.tangent(u, k, modified=True, shift=SHIFT * 1e-3)
                mg = ReusedHierarchy(amg_hierarchy(reference, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def linear_response(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m, of ``load_case``'s list linearised at rest (each spring
        acting along its rest direction) under nodal ``loads`` (N, 3), N; zero off the list.

        Solved to a relative residual of ``rtol`` (LU or multigrid CG as for Newton steps; the
        solve does not count towards the hierarchy's staleness); CG starts from ``guess``
        ((N, 3), m; e.g. a reduced model's answer) when given.

        Raises:
            SingularStiffnessError, NegativeCurvature: the linear lattice is not held (e.g. an
                'axis' lattice at rest is a mechanism).
        """
        system, _ = self.system(load_case, depth)
        k = system.parameters(Stiffness.of(stiffness))
        tangent = system.tangent(np.zeros((system.n_free, 3)), k, modified=True)
        return self.linear_solve(load_case, depth, tangent, loads, guess=guess, rtol=rtol)

    def linear_solve(
        self,
        load_case: int,
        depth: int | None,
        tangent: sp.sparray | sp.spmatrix,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m: ``tangent`` (3M, 3M) (a stiffness over the list's free
        nodes, e.g. :meth:`SpringSystem.tangent` at rest) solved for nodal ``loads`` (N, 3), N,
        as :meth:`linear_response` does; zero off the list. ``rtol`` >= 1 asks for one
        multigrid V-cycle only (LU is exact below AMG_FROM_UNKNOWNS)."""
        system, _ = self.system(load_case, depth)
        rhs = np.ascontiguousarray(loads[system.free]).ravel()
        if 3 * system.n_free < self.amg_from:
            x = _direct_solve(tangent, rhs)
        elif rtol >= 1.0:  # one multigrid V-cycle: an approximate answer, for search directions
            x = self._linear_hierarchy(system, tangent).precondition(rhs)
        else:
            start = np.zeros_like(rhs)
            if guess is not None:
                start = np.ascontiguousarray(guess[system.free]).ravel()
            left = rhs - tangent @ start
            size, remaining = float(np.linalg.norm(rhs)), float(np.linalg.norm(left))
            x = start
            if remaining > rtol * size:
                mg = self._linear_hierarchy(system, tangent)
                cg = conjugate_gradients(
                    tangent, left, mg.precondition, rtol=rtol * size / remaining,
                    max_iterations=10 * MAX_CG_ITERATIONS,
                )  # fmt: skip
                x = start + cg.x
        out = np.zeros_like(self.problem.nodes)
        out[system.free] = x.reshape(-1, 3)
        return out


def _galerkin(
    system: SpringSystem,
    k: Params,
    forces: np.ndarray,
    u: np.ndarray,
    gradient: np.ndarray,
    basis: np.ndarray,
    target: float,
    stats: _Stats,
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise E over u + span(basis) (basis (M, 3, m) orthonormal): chord-Newton steps on
    the m x m reduced tangent Q^T K Q at the start (exact; clamped where the exact one is not
    positive definite), each with an Armijo line search on E.

    One reduced tangent per solve: it costs O(A m^2), against O(A) for a gradient; the answer
    in the span is limited by the span rather than by these iterations (measured: exact
    Newton in the span gets no closer).
    """
    m = basis.shape[2]
    q = basis.reshape(-1, m)
    for modified in (False, True):
        hessian = system.reduced_tangent(u, k, basis, modified)
        if np.all(np.isfinite(hessian)) and np.linalg.eigvalsh(hessian).min() > 0:
            break
    else:
        return u, gradient
    first = None
    for _ in range(GALERKIN_ITERATIONS):
        reduced = np.einsum("ia,i->a", q, gradient.ravel())
        size = float(np.linalg.norm(reduced))
        first = size if first is None else first
        if size <= 1e-6 * first:
            break
        coefficients = -np.linalg.solve(hessian, reduced)
        step = np.einsum("ia,a->i", q, coefficients).reshape(-1, 3)
        slope = float(np.dot(reduced, coefficients))
        if not slope < 0:
            break
        alpha = 1.0
        for _ in range(8):
            if system.energy_change(u, alpha * step, k, forces) <= ARMIJO * alpha * slope:
                break
            alpha *= 0.5
        else:
            break
        u = u + alpha * step
        gradient = system.gradient(u, k, forces)
        stats.reduced_iterations += 1
        if _largest(gradient) <= target:
            break
    return u, gradient


def _direct_solve(tangent: sp.bsr_matrix, rhs: np.ndarray) -> np.ndarray:
    """Sparse LU solve (:func:`fpm.fem.linear_solver.factorize`).

    Raises:
        SingularStiffnessError: the tangent is singular, or the solve is not finite.
    """
    x = factorize(tangent.tocsc(), "direct", np.zeros((0, 6)))(rhs)
    if not np.all(np.isfinite(x)):
        raise SingularStiffnessError("the LU solve is not finite")
    return np.asarray(x)


def _largest(vectors: np.ndarray) -> float:
    """Largest Euclidean norm of the rows of ``vectors`` (M, 3)."""
    if not len(vectors):
        return 0.0
    return float(np.sqrt(np.einsum("ij,ij->i", vectors, vectors).max()))


_SOLVERS = threading.Lock()


def static_solver(problem: Problem) -> StaticSolver:
    """This thread's :class:`StaticSolver` of ``problem``, built on first use and kept on the
    problem (``problem.cache["static_solvers"]``, one per thread)."""
    local = problem.cache.get("static_solvers")
    if local is None:
        with _SOLVERS:
            local = problem.cache.setdefault("static_solvers", threading.local())
    solver = getattr(local, "solver", None)
    if solver is None:
        solver = local.solver = StaticSolver(problem)
    return solver


def static_equilibrium(
    problem: Problem,
    *,
    k: float | Sequence[float] | np.ndarray,
    depth: int | None = None,
    load_case: int = 0,
    tolerance: float | None = None,
) -> Equilibrium:
    """The static equilibrium of one load case (what a settled :func:`fpm.simulate` reaches).

    Args:
        problem: from :func:`fpm.load_problem`.
        k: spring stiffness, N/m: one value for every spring, or one per spring family
            (:func:`fpm.model.stiffness.spring_stiffness`; the spec's stiffness_scale applies).
        depth: penetration depth in layers; None = the spec's (its 'auto' means all layers).
        load_case: index into the spec's load cases.
        tolerance: relative force tolerance; None = a tenth of the spec's settle_tolerance.

    Uses this thread's cached :class:`StaticSolver`, so repeated calls start warm.
    """
    if not 0 <= load_case < len(problem.load_cases):
        raise ValueError(f"load_case must be in 0..{len(problem.load_cases) - 1}")
    if not np.all(np.asarray(k, dtype=float) > 0):
        raise ValueError("need k > 0")
    if depth is None and problem.spec.fpm.depth != "auto":
        depth = int(problem.spec.fpm.depth)
    if depth is not None and depth < 0:
        raise ValueError("depth must be >= 0")
    stiffness = model_stiffness(problem, k)
    return static_solver(problem).solve(load_case, stiffness, depth, tolerance=tolerance)
