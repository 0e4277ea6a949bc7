"""The FPM time step (paper Eq. 1, Voigt model), compiled: the one hot loop of the project.

One step visits the perturbed list node by node, always using the newest positions
(physics.md): for node i with mass m_i, external force F_i and springs to j,

    F_s = sum_j k_ij (|r_ij| - l_ij) r_ij / |r_ij|,     r_ij = x_j - x_i
    v_i <- (v_i + dt (F_i + F_s) / m_i) / (1 + dt d / m_i)      (damping taken implicitly)
    x_i <- x_i + dt v_i

With the volume term (:mod:`fpm.model.volume`), F_i also holds the volume forces
-kappa_c (V_c - V0_c) / V0_c dV_c/dx_i of the cells around node i. They are computed once per
step, at its start, in one pass over the cells that touch the list (a cell acts when any of its
corners is in the list): a cell's volume depends on all 8 corners, so refreshing it after every
node would cost 8 volume gradients per node instead of one per cell. The springs keep the
paper's node-by-node order. A settled run is the same static equilibrium either way (nothing
moves there), which the tests check against :mod:`fpm.dynamics.equilibrium`.

The loop is sequential by nature (each node sees its predecessors' new positions), so it is
compiled with numba rather than vectorised; compilation is cached on disk, and the GIL is
released so that annealing chains can run on threads.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..model.volume import COEFFICIENTS, coefficient_gradient, corner_gradient, volume_of

RUNNING, SETTLED, DIVERGED = 0, 1, 2
INVERTED = 3
"""A cell's volume reached zero or below (the run stops; :func:`volume_forces` names it)."""


@njit(cache=True, nogil=True)
def volume_forces(
    corners: np.ndarray,
    rest_coefficients: np.ndarray,
    rest_volume: np.ndarray,
    kappa: np.ndarray,
    x: np.ndarray,
    order: np.ndarray,
    out: np.ndarray,
) -> int:
    """Set ``out`` (N, 3) at the list nodes ``order`` to their volume forces at positions ``x``,
    N, from cells ``corners`` (C, 8) with rest a1..a6 ``rest_coefficients`` (C, 6, 3), rest
    volumes (C,) m^3 and ``kappa`` (C,) Pa. Returns -1, or the first cell whose volume is not
    positive (an inverted cell)."""
    for i in order:
        out[i, 0] = out[i, 1] = out[i, 2] = 0.0
    a = np.empty((6, 3))
    grad_a = np.empty((6, 3))
    grad_x = np.empty((8, 3))
    for c in range(corners.shape[0]):
        for k in range(6):
            for d in range(3):
                value = 0.0
                for n in range(8):
                    value += COEFFICIENTS[k, n] * x[corners[c, n], d]
                a[k, d] = value
        volume = volume_of(a)
        if not volume > 0.0:
            return c
        pressure = kappa[c] * (volume - rest_volume[c]) / rest_volume[c]
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        for n in range(8):
            node = corners[c, n]
            for d in range(3):
                out[node, d] -= pressure * grad_x[n, d]
    return -1


@njit(cache=True, nogil=True)
def run_steps(
    order: np.ndarray,
    ptr: np.ndarray,
    neighbour: np.ndarray,
    rest_length: np.ndarray,
    stiffness_factor: np.ndarray,
    rest: np.ndarray,
    x: np.ndarray,
    v: np.ndarray,
    external: np.ndarray,
    mass: np.ndarray,
    k: float,
    d: float,
    dt: float,
    max_steps: int,
    settle_force: float,
    max_move: float,
    corners: np.ndarray,
    rest_coefficients: np.ndarray,
    rest_volume: np.ndarray,
    kappa: np.ndarray,
    volume_force: np.ndarray,
) -> tuple[int, int, float, int]:
    """Advance ``x``, ``v`` (N, 3) in place by up to ``max_steps`` steps over ``order`` (M,).

    ``external`` (N, 3) is F_i, N; ``mass`` (N,) kg; ``stiffness_factor`` (2S,) or empty (all 1);
    ``rest`` (N, 3) the rest positions. The volume term's cells (``corners`` (C, 8) ... ``kappa``
    as :func:`volume_forces`; C = 0: none) add their forces, kept in ``volume_force`` (N, 3).
    Stops early once the largest |F_i + F_s| of a sweep is below ``settle_force`` (N), once a
    node is non-finite or further than ``max_move`` (m) from rest (DIVERGED), or once a cell
    inverts (INVERTED). Returns (steps taken, RUNNING/SETTLED/DIVERGED/INVERTED, largest
    |F_i + F_s| of the last sweep, the inverted cell or -1).
    """
    scaled = stiffness_factor.shape[0] > 0
    cells = corners.shape[0] > 0
    limit2 = max_move * max_move
    worst = 0.0
    for step in range(1, max_steps + 1):
        worst2 = 0.0
        if cells:
            inverted = volume_forces(
                corners, rest_coefficients, rest_volume, kappa, x, order, volume_force
            )
            if inverted >= 0:
                return step, INVERTED, worst, inverted
        for i in order:
            xi0, xi1, xi2 = x[i, 0], x[i, 1], x[i, 2]
            f0, f1, f2 = external[i, 0], external[i, 1], external[i, 2]
            if cells:
                f0 += volume_force[i, 0]
                f1 += volume_force[i, 1]
                f2 += volume_force[i, 2]
            for e in range(ptr[i], ptr[i + 1]):
                j = neighbour[e]
                r0 = x[j, 0] - xi0
                r1 = x[j, 1] - xi1
                r2 = x[j, 2] - xi2
                length = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                s = k * (length - rest_length[e]) / length
                if scaled:
                    s *= stiffness_factor[e]
                f0 += s * r0
                f1 += s * r1
                f2 += s * r2
            f2sum = f0 * f0 + f1 * f1 + f2 * f2
            if f2sum > worst2:
                worst2 = f2sum
            a = dt / mass[i]
            damp = 1.0 / (1.0 + a * d)
            v0 = (v[i, 0] + a * f0) * damp
            v1 = (v[i, 1] + a * f1) * damp
            v2 = (v[i, 2] + a * f2) * damp
            v[i, 0], v[i, 1], v[i, 2] = v0, v1, v2
            xi0 += dt * v0
            xi1 += dt * v1
            xi2 += dt * v2
            x[i, 0], x[i, 1], x[i, 2] = xi0, xi1, xi2
            u0, u1, u2 = xi0 - rest[i, 0], xi1 - rest[i, 1], xi2 - rest[i, 2]
            if not (u0 * u0 + u1 * u1 + u2 * u2 <= limit2):  # also catches NaN
                return step, DIVERGED, np.sqrt(worst2), -1
        worst = np.sqrt(worst2)
        if worst < settle_force:
            return step, SETTLED, worst, -1
    return max_steps, RUNNING, worst, -1
