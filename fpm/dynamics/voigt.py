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

RUNNING, SETTLED, DIVERGED = 0, 1, 2
INVERTED = 3
"""A cell's volume reached zero or below (the run stops; :func:`volume_forces` names it)."""


BLOCK = 32
"""Cells processed together by :func:`volume_forces`: its arithmetic runs over a block of cells
in the innermost loop, which the compiler vectorises (SIMD)."""


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
    N, from cells ``corners`` (C, 8) with rest volumes (C,) m^3 and ``kappa`` (C,) Pa
    (``rest_coefficients`` (C, 6, 3) is unused here: positions are absolute). Returns -1, or
    the first cell whose volume is not positive (an inverted cell).

    The formulas of :mod:`fpm.model.volume`, written out for speed: a1..a6 of a cell by
    butterflies over its corners (sums and differences along r, then s and t), dV/da_k by
    cross products, V = (sum_k a_k . dV/da_k) / 3 (V is homogeneous of degree 3 in a1..a6),
    and dV/dx_n = (r_n B + A) / 8 with A = s G2 + t G3 + st G6, B = G1 + s G4 + t G5 per
    (s_n, t_n). Blocks of :data:`BLOCK` cells: gather, vectorised arithmetic, scatter.
    """
    for i in order:
        out[i, 0] = out[i, 1] = out[i, 2] = 0.0
    xb = np.empty((8, 3, BLOCK))
    a = np.empty((7, 3, BLOCK))  # a[1..6]
    g = np.empty((7, 3, BLOCK))  # dV/da_k, k = 1..6
    pressure = np.empty(BLOCK)
    w3, w1 = 8.0, 8.0 / 3.0
    for start in range(0, corners.shape[0], BLOCK):
        nb = min(BLOCK, corners.shape[0] - start)
        for n in range(8):
            for b in range(nb):
                node = corners[start + b, n]
                xb[n, 0, b] = x[node, 0]
                xb[n, 1, b] = x[node, 1]
                xb[n, 2, b] = x[node, 2]
        for d in range(3):
            for b in range(nb):
                p00 = xb[1, d, b] - xb[0, d, b]
                q00 = xb[1, d, b] + xb[0, d, b]
                p10 = xb[2, d, b] - xb[3, d, b]
                q10 = xb[2, d, b] + xb[3, d, b]
                p01 = xb[5, d, b] - xb[4, d, b]
                q01 = xb[5, d, b] + xb[4, d, b]
                p11 = xb[6, d, b] - xb[7, d, b]
                q11 = xb[6, d, b] + xb[7, d, b]
                a[1, d, b] = 0.125 * (p00 + p10 + p01 + p11)
                a[2, d, b] = 0.125 * (-q00 + q10 - q01 + q11)
                a[3, d, b] = 0.125 * (-q00 - q10 + q01 + q11)
                a[4, d, b] = 0.125 * (-p00 + p10 - p01 + p11)
                a[5, d, b] = 0.125 * (-p00 - p10 + p01 + p11)
                a[6, d, b] = 0.125 * (q00 - q10 - q01 + q11)
        # dV/da_k: V = w3 [a1, a2, a3] + w1 ([a1, a4, a5] + [a4, a2, a6] + [a5, a6, a3]).
        for d in range(3):
            e, f = (d + 1) % 3, (d + 2) % 3
            for b in range(nb):
                g[1, d, b] = w3 * (a[2, e, b] * a[3, f, b] - a[2, f, b] * a[3, e, b]) + w1 * (
                    a[4, e, b] * a[5, f, b] - a[4, f, b] * a[5, e, b]
                )
                g[2, d, b] = w3 * (a[3, e, b] * a[1, f, b] - a[3, f, b] * a[1, e, b]) + w1 * (
                    a[6, e, b] * a[4, f, b] - a[6, f, b] * a[4, e, b]
                )
                g[3, d, b] = w3 * (a[1, e, b] * a[2, f, b] - a[1, f, b] * a[2, e, b]) + w1 * (
                    a[5, e, b] * a[6, f, b] - a[5, f, b] * a[6, e, b]
                )
                g[4, d, b] = w1 * (
                    a[5, e, b] * a[1, f, b]
                    - a[5, f, b] * a[1, e, b]
                    + a[2, e, b] * a[6, f, b]
                    - a[2, f, b] * a[6, e, b]
                )
                g[5, d, b] = w1 * (
                    a[1, e, b] * a[4, f, b]
                    - a[1, f, b] * a[4, e, b]
                    + a[6, e, b] * a[3, f, b]
                    - a[6, f, b] * a[3, e, b]
                )
                g[6, d, b] = w1 * (
                    a[4, e, b] * a[2, f, b]
                    - a[4, f, b] * a[2, e, b]
                    + a[3, e, b] * a[5, f, b]
                    - a[3, f, b] * a[5, e, b]
                )
        for b in range(nb):
            volume = 0.0
            for k in range(1, 7):
                volume += (
                    a[k, 0, b] * g[k, 0, b] + a[k, 1, b] * g[k, 1, b] + a[k, 2, b] * g[k, 2, b]
                )
            volume /= 3.0
            if not volume > 0.0:
                return start + b
            c = start + b
            pressure[b] = 0.125 * kappa[c] * (volume - rest_volume[c]) / rest_volume[c]
        # Corner forces -p dV/dx_n, scattered.
        for d in range(3):
            for b in range(nb):
                pb = pressure[b]
                g1, g2, g3 = g[1, d, b], g[2, d, b], g[3, d, b]
                g4, g5, g6 = g[4, d, b], g[5, d, b], g[6, d, b]
                a_mm, b_mm = -g2 - g3 + g6, g1 - g4 - g5  # (s, t) = (-, -)
                a_pm, b_pm = g2 - g3 - g6, g1 + g4 - g5  # (+, -)
                a_mp, b_mp = -g2 + g3 - g6, g1 - g4 + g5  # (-, +)
                a_pp, b_pp = g2 + g3 + g6, g1 + g4 + g5  # (+, +)
                xb[0, d, b] = -pb * (a_mm - b_mm)
                xb[1, d, b] = -pb * (a_mm + b_mm)
                xb[3, d, b] = -pb * (a_pm - b_pm)
                xb[2, d, b] = -pb * (a_pm + b_pm)
                xb[4, d, b] = -pb * (a_mp - b_mp)
                xb[5, d, b] = -pb * (a_mp + b_mp)
                xb[7, d, b] = -pb * (a_pp - b_pp)
                xb[6, d, b] = -pb * (a_pp + b_pp)
        for n in range(8):
            for b in range(nb):
                node = corners[start + b, n]
                out[node, 0] += xb[n, 0, b]
                out[node, 1] += xb[n, 1, b]
                out[node, 2] += xb[n, 2, b]
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
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
    settle_stiffness: float,
    max_move: float,
    corners: np.ndarray,
    rest_coefficients: np.ndarray,
    rest_volume: np.ndarray,
    kappa: np.ndarray,
    volume_force: np.ndarray,
    target: np.ndarray,
    slowness: float,
    reach: float,
) -> tuple[int, int, float, int, float, float]:
    """Advance ``x``, ``v`` (N, 3) in place by up to ``max_steps`` steps over ``order`` (M,).

    ``external`` (N, 3) is F_i, N; ``mass`` (N,) kg; ``stiffness_factor`` (2S,) or empty (all 1);
    ``rest`` (N, 3) the rest positions. The volume term's cells (``corners`` (C, 8) ... ``kappa``
    as :func:`volume_forces`; C = 0: none) add their forces, kept in ``volume_force`` (N, 3).
    Stops early (SETTLED) once the largest |F_i + F_s| of a sweep is below ``settle_force``
    (N; the force criterion), or once the 2-norm of the sweep's F_i + F_s over the list is
    below ``settle_stiffness`` (N/m) times the 2-norm of its x_i - rest_i (the distance
    criterion of :mod:`fpm.dynamics.settle`; 0 for none), or, with ``target`` (N, 3) the static
    equilibrium's positions (m; (0, 3): none), once the sweep's *reach*
    ``sum_i sqrt(|x_i - target_i|^2 + slowness m_i |v_i|^2)`` (m; ``slowness`` m/N) is below
    ``reach`` (m; the target criterion of :mod:`fpm.dynamics.settle`; it is then the fifth
    value returned, in place of the forces' 2-norm); once a node is non-finite or further
    than ``max_move`` (m) from rest (DIVERGED; two nodes at one place give a non-finite force,
    NumPy's error model, rather than an exception), or once a cell inverts (INVERTED). Returns
    (steps taken, RUNNING/SETTLED/DIVERGED/INVERTED, largest |F_i + F_s| of the last sweep,
    the inverted cell or -1, the 2-norms of the last sweep's F_i + F_s (N) and x_i - rest_i
    (m)).
    """
    scaled = stiffness_factor.shape[0] > 0
    cells = corners.shape[0] > 0
    targeted = target.shape[0] > 0
    limit2 = max_move * max_move
    worst = norm = moved = 0.0
    most = 0
    for i in order:
        most = max(most, ptr[i + 1] - ptr[i])
    r0s = np.empty(most)  # one node's springs
    r1s = np.empty(most)
    r2s = np.empty(most)
    for step in range(1, max_steps + 1):
        worst2 = 0.0
        total2 = 0.0
        moved2 = 0.0
        reached = 0.0
        if cells:
            inverted = volume_forces(
                corners, rest_coefficients, rest_volume, kappa, x, order, volume_force
            )
            if inverted >= 0:
                return step, INVERTED, worst, inverted, norm, moved
        for i in order:
            xi0, xi1, xi2 = x[i, 0], x[i, 1], x[i, 2]
            f0, f1, f2 = external[i, 0], external[i, 1], external[i, 2]
            if cells:
                f0 += volume_force[i, 0]
                f1 += volume_force[i, 1]
                f2 += volume_force[i, 2]
            # The node's springs in three passes: gather r = x_j - x_i; each spring's force
            # s r (a loop without indirect loads, which the compiler vectorises: the square
            # roots and divisions, the step's costliest arithmetic, 8 springs at a time); sum
            # them in the neighbours' order. Every value is the one the single loop computed,
            # summed in the same order: positions identical to the bit.
            first = ptr[i]
            n = ptr[i + 1] - first
            for t in range(n):
                j = neighbour[first + t]
                r0s[t] = x[j, 0] - xi0
                r1s[t] = x[j, 1] - xi1
                r2s[t] = x[j, 2] - xi2
            rest_lengths = rest_length[first : first + n]
            if scaled:
                factors = stiffness_factor[first : first + n]
                for t in range(n):
                    r0 = r0s[t]
                    r1 = r1s[t]
                    r2 = r2s[t]
                    length = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                    s = k * (length - rest_lengths[t]) / length
                    s *= factors[t]
                    r0s[t] = s * r0
                    r1s[t] = s * r1
                    r2s[t] = s * r2
            else:
                for t in range(n):
                    r0 = r0s[t]
                    r1 = r1s[t]
                    r2 = r2s[t]
                    length = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                    s = k * (length - rest_lengths[t]) / length
                    r0s[t] = s * r0
                    r1s[t] = s * r1
                    r2s[t] = s * r2
            for t in range(n):
                f0 += r0s[t]
                f1 += r1s[t]
                f2 += r2s[t]
            f2sum = f0 * f0 + f1 * f1 + f2 * f2
            if f2sum > worst2:
                worst2 = f2sum
            total2 += f2sum
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
            u2sum = u0 * u0 + u1 * u1 + u2 * u2
            if not (u2sum <= limit2):  # also catches NaN
                return step, DIVERGED, np.sqrt(worst2), -1, np.sqrt(total2), np.sqrt(moved2)
            moved2 += u2sum
            if targeted:
                e0, e1, e2 = xi0 - target[i, 0], xi1 - target[i, 1], xi2 - target[i, 2]
                kinetic = slowness * mass[i] * (v0 * v0 + v1 * v1 + v2 * v2)
                reached += np.sqrt(e0 * e0 + e1 * e1 + e2 * e2 + kinetic)
        worst = np.sqrt(worst2)
        norm = reached if targeted else np.sqrt(total2)
        moved = np.sqrt(moved2)
        if targeted:
            if norm < reach:
                return step, SETTLED, worst, -1, norm, moved
        elif worst < settle_force or norm < settle_stiffness * moved:
            return step, SETTLED, worst, -1, norm, moved
    return max_steps, RUNNING, worst, -1, norm, moved
