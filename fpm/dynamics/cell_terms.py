"""The volume term in the static solver: compiled (numba) loops over the active cells of a
:class:`~fpm.dynamics.spring_system.SpringSystem`.

Each cell c (an 8-node hexahedron, :mod:`fpm.model.volume`) carries the energy

    W_c = 1/2 kappa_c (V_c - V0_c)^2 / V0_c,

kappa_c its volume stiffness, Pa, V_c its volume and V0_c its rest volume, m^3. With
g = dV_c/dx (8 corners x 3, m^2) and the pressure p = kappa_c (V_c - V0_c) / V0_c, Pa:

- gradient: dW_c/dx_n = p g_n, N (:func:`_cell_forces`);
- energy change W_c(u + step) - W_c(u) = 1/2 kappa_c / V0_c (dV' - dV)(dV' + dV), the volume
  change dV' - dV computed without cancellation (:func:`_cell_energy_change`);
- tangent, 3x3 per pair of corners: (kappa_c / V0_c) g_n g_m^T + p d^2V/dx_n dx_m, N/m;
  "modified" drops the p term, leaving a positive semi-definite part
  (:func:`_cell_tangent_blocks`); on a basis Q (M, 3, m) the modified part only,
  (kappa_c / V0_c) (Q^T g)(Q^T g)^T (:func:`_cell_reduced_tangent`);
- the gradient's derivative by kappa_c, (dV / V0) g, against a field w (M, 3):
  (dV / V0) sum_n g_n . w_n (:func:`_cell_sensitivity`; a field fit's adjoint gradient).

Arrays: ``rest`` (C, 6, 3) a1..a6 of each cell at rest, m (:class:`fpm.model.volume.Cells`);
``volume`` (C,) V0, m^3; ``ends`` (C, 8) local indices of each cell's corners among the free
nodes (-1: a held corner, which stays at rest); ``kappa`` (C,) Pa; displacements ``u`` and
``step`` (M, 3), m. The volume, its gradient and Hessian per cell come from
:mod:`fpm.model.volume`; the kernels add into the caller's arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..model.volume import (
    _TRIPLES,
    COEFFICIENTS,
    coefficient_gradient,
    coefficient_hessian,
    corner_gradient,
    volume_change,
)

_PAIRS = np.array(
    sorted({(i, j) for p, q, r, _ in _TRIPLES for i in (p, q, r) for j in (p, q, r) if i != j}),
    dtype=np.int64,
)
"""(24, 2) the (k, q) with d^2 V / da_k da_q not identically zero: a_k, a_q in one triple
product of the volume (in ascending order, as the full loop visits them)."""


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
            # Only the nonzero terms: d^2V/da_k da_q is zero unless a_k and a_q share one of
            # the volume's triple products (24 of the 36 blocks), and each block is a cross
            # product's matrix, zero on its diagonal, as is then every sum of them. Skipping
            # a term 0 * c changes no sum: the blocks are those of the full loops, to the bit.
            coefficient_hessian(a, hessian_a)
            half[:] = 0.0
            for pair in range(len(_PAIRS)):
                k, q = _PAIRS[pair, 0], _PAIRS[pair, 1]
                for m in range(8):
                    cq = COEFFICIENTS[q, m]
                    for x in range(3):
                        for y in range(3):
                            if x != y:
                                half[k, m, x, y] += hessian_a[k, q, x, y] * cq
            hessian_x[:] = 0.0
            for k in range(6):
                for n in range(8):
                    ck = COEFFICIENTS[k, n]
                    for m in range(8):
                        for x in range(3):
                            for y in range(3):
                                if x != y:
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
def _cell_sensitivity(
    rest: np.ndarray,
    volume: np.ndarray,
    ends: np.ndarray,
    u: np.ndarray,
    w: np.ndarray,
    out: np.ndarray,
) -> None:
    """Fill ``out`` (C,) with w . d(dE/du)/d kappa_c = (V_c - V0_c) / V0_c sum_n g_n . w_n,
    m, at displacements u (M, 3) for the field w (M, 3) (held corners contribute nothing)."""
    a, da = np.empty((6, 3)), np.empty((6, 3))
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    for c in range(len(volume)):
        _cell_state(rest, ends, u, c, a, da)
        strain = volume_change(rest[c], da) / volume[c]
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        total = 0.0
        for n in range(8):
            i = ends[c, n]
            if i >= 0:
                total += grad_x[n, 0] * w[i, 0] + grad_x[n, 1] * w[i, 1] + grad_x[n, 2] * w[i, 2]
        out[c] = strain * total
