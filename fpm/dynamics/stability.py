"""The lattice's stability estimate for the FPM step, and the time step 'auto'.

The derivation, for the step of :mod:`fpm.dynamics.voigt` (semi-implicit Euler, node by node,
damping taken implicitly)::

    v_i <- (v_i + dt F_i / m_i) / (1 + dt d / m_i),     x_i <- x_i + dt v_i

1. One mode, all nodes updated at once, no damping. Near rest the spring forces are linear,
   F = -K u (K: each spring ij adds k_ij e e^T to the diagonal 3x3 blocks of i and j and
   -k_ij e e^T to the off-diagonal ones, e its unit vector), so a mode of M^-1 K with
   eigenvalue w^2 evolves as (u, dt v) <- A (u, dt v) with A = [[1 - s, 1], [-s, 1]],
   s = (w dt)^2: trace 2 - s, determinant 1. Its eigenvalues stay on the unit circle while
   |2 - s| < 2, i.e. w dt < 2. So dt_max = 2 / w_max with w_max^2 = lambda_max(M^-1 K).
2. Implicit damping, c = dt d / m: trace (2 + c - s) / (1 + c), determinant 1 / (1 + c); the
   Jury conditions give s < 4 + 2c. Damping only raises the limit, so the estimate ignores it:
   it holds for every d >= 0 as far as this mode analysis goes.
3. Gershgorin's theorem by 3x3 block rows of M^-1 K (Feingold and Varga; over the nodes that
   move; ||e e^T|| = 1): the diagonal block of node i has eigenvalues at most sum_j k_ij / m_i,
   its off-diagonal blocks add at most as much again (springs to fixed nodes add none), so
   w_max^2 <= 2 max_i (sum_j k_ij) / m_i = 2 q, and

       dt_max = 2 / sqrt(2 q) = sqrt(2 / q),   q = max_i (sum_j k_ij) / m_i,

   the sum over every spring of node i (springs to fixed nodes included), i over free nodes.
   Light surface nodes with few springs often have the largest ratio.
4. Node-by-node order. Node i sees its predecessors' new positions; linearised,
   M (u+ - 2u + u-) = -dt^2 (K u + L (u+ - u)), L the strictly lower part of K in list order.
   The extra term, -dt^3 L v+, is not symmetric: it feeds energy into modes whose neighbours
   move against each other, so without damping the step is weakly unstable at every dt, and
   with damping its limit sits below the all-at-once one; the factor 2 of step 3 roughly pays
   for the order (tests/core/test_volume.py, tests/core/test_diagnosis.py). dt_max is an
   estimate, not a guarantee: take dt at most about dt_max, and enough damping.
5. The volume term. Near rest a cell c adds (kappa_c / V0_c) g g^T to K (g = dV_c/dx, 24
   values, at rest): the 3x3 block (i, n) is (kappa_c / V0_c) g_i g_n^T, of norm
   (kappa_c / V0_c) |g_i| |g_n|. Gershgorin's row sum of node i therefore grows by
   ``r_i = sum_c (kappa_c / V0_c) |g_ci| sum_n |g_cn|`` over its cells, and

       dt_max = 2 / sqrt(max_i (2 sum_j k_ij + r_i) / m_i)

   (without cells, the formula of step 3).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model.forces import Stiffness, cells
from ..model.problem import Problem
from ..model.spec import MAX_DT

AUTO_FRACTION = 0.5
"""dt 'auto' is this fraction of :func:`stable_time_step` (at most MAX_DT)."""


def stable_time_step(problem: Problem, stiffness: float | np.ndarray | Stiffness) -> float:
    """The lattice's stability estimate for the FPM step, dt_max, s (this module's docstring).

    Args:
        problem: the problem.
        stiffness: the model's :class:`~fpm.model.forces.Stiffness`, or (S,) stiffness of every
            spring, N/m (as :func:`fpm.model.stiffness.spring_stiffness` gives, stiffness_scale
            included), or one k for every spring (the spec's stiffness_scale is then applied).

    Returns:
        dt_max, s (inf if no free node has a spring or a cell).
    """
    solid = problem.solid
    kappa = stiffness.volume if isinstance(stiffness, Stiffness) else None
    k = np.asarray(stiffness.springs if isinstance(stiffness, Stiffness) else stiffness, float)
    if k.ndim == 0:
        from ..model.stiffness import spring_stiffness

        k = spring_stiffness(problem, float(k))
    if k.shape != (len(solid.springs),):
        raise ValueError(
            f"stiffness has shape {k.shape}: give one value, or one per spring "
            f"({len(solid.springs)},)"
        )
    rows = 2.0 * np.bincount(
        solid.springs.ravel(), weights=np.repeat(k, 2), minlength=problem.n_nodes
    )
    if kappa is not None:
        rows += volume_rows(problem, kappa)
    free = ~problem.fixed
    if not free.any():
        return float("inf")
    top = float((rows[free] / solid.masses[free]).max())
    return float(2.0 / np.sqrt(top)) if top > 0 else float("inf")


def volume_rows(problem: Problem, kappa: np.ndarray) -> np.ndarray:
    """(N,) r_i = sum_c (kappa_c / V0_c) |g_ci| sum_n |g_cn| at rest, N/m (step 5)."""
    from ..model.volume import coefficient_gradient, corner_gradient

    c = cells(problem)
    norms = np.empty((len(c.volume), 8))
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    for i, a in enumerate(c.rest):
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        norms[i] = np.linalg.norm(grad_x, axis=1)
    weight = (np.asarray(kappa, float) / c.volume)[:, None] * norms * norms.sum(axis=1)[:, None]
    return np.bincount(c.corners.ravel(), weights=weight.ravel(), minlength=problem.n_nodes)


def auto_time_step(problem: Problem, stiffness: float | np.ndarray | Stiffness) -> float:
    """dt 'auto', s: :data:`AUTO_FRACTION` of :func:`stable_time_step`, at most MAX_DT."""
    return float(min(MAX_DT, AUTO_FRACTION * stable_time_step(problem, stiffness)))


def time_step(problem: Problem, stiffness: Any) -> float:
    """The spec's dt, s, or for 'auto' :func:`auto_time_step` at ``stiffness``."""
    dt = problem.spec.fpm.dt
    return auto_time_step(problem, stiffness) if dt == "auto" else float(dt)
