"""Diagnoses for the user: a reference in the wrong units, a time step the lattice cannot take,
and why an annealing start failed. Every message says what to change.

The stability estimate (:func:`stable_time_step`), derived for the step of :mod:`fpm.dynamics.voigt`
(semi-implicit Euler, node by node, damping taken implicitly)::

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
   w_max^2 <= 2 max_i (sum_j k_ij) / m_i = 2 kappa, and

       dt_max = 2 / sqrt(2 kappa) = sqrt(2 / kappa),   kappa = max_i (sum_j k_ij) / m_i,

   the sum over every spring of node i (springs to fixed nodes included), i over free nodes.
   Light surface nodes with few springs often have the largest ratio.
4. Node-by-node order. Node i sees its predecessors' new positions; linearised,
   M (u+ - 2u + u-) = -dt^2 (K u + L (u+ - u)), L the strictly lower part of K in list order.
   The extra term, -dt^3 L v+, is not symmetric: it feeds energy into modes whose neighbours
   move against each other, so without damping the step is weakly unstable at every dt (the
   spectral radius is about 1 + 0.1 (dt / dt_max)^2 per step on examples/small-box.json with
   k = 38.8 N/m), and with damping its limit sits below the all-at-once one. Measured on
   small-box, the paper's cube (k = 38.8 N/m) and bench/organ.py's ellipsoid (h = 10 mm,
   k = 20 N/m) with d = 0.5 sqrt(E h m) (m the mean node mass; the default d range is 0.1 to 5
   times that): runs at 0.5 dt_max settle, at 1.0 dt_max they do not diverge, at 1.5 dt_max
   they do (at 1.25 already on the cube and the ellipsoid), at 3 dt_max within a few steps.
   With d = 0.3 sqrt(E h m), 1.0 dt_max already diverges; with 0.1, runs diverge even at
   0.5 dt_max. The factor 2 of step 3 (about 1.5 too generous for the all-at-once step: its
   true limit is 1.7 dt_max on small-box) thus roughly pays for the order. dt_max is an
   estimate, not a guarantee: take dt at most about dt_max, and enough damping.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..model.problem import Problem

UNITS_HINT = "E is in Pa (5 kPa = 5000), lengths in m, forces in N"
SMALL_STRAIN = 0.1
"""A reference displacement above this fraction of the solid's smallest extent is flagged."""

REJECTIONS = ("diverged", "unsettled", "no equilibrium", "c_max")
"""The keys :func:`explain_rejections` knows: a candidate diverged, did not settle within
max_steps, had no static equilibrium, or cost more than c_max."""


class UnitsError(ValueError):
    """The FEM reference moves a node further than the solid is thick: the units are wrong."""


def check_reference(problem: Problem, displacements: Any) -> list[str]:
    """Check that the FEM reference is plausible; return warnings (one line each).

    Args:
        problem: the problem.
        displacements: (L, N, 3) FEM displacements, m (or a :class:`fpm.fem.reference.FemResult`).

    Returns:
        For the linear model, one warning per load case whose largest nodal displacement is
        above 10% of the solid's smallest bounding-box extent (outside small strain, where a
        linear reference is only approximate); none for the neo-Hookean model, which is made
        for large deformation.

    Raises:
        UnitsError: a load case moves a node further than the smallest extent: with linear
            elasticity this almost always means the units are off (E = 5 for 5 kPa, a size in
            mm, a force in g); otherwise (a slender part under a large load) the linear
            reference is meaningless there anyway.
    """
    u = np.asarray(getattr(displacements, "displacements", displacements), dtype=float)
    linear = problem.spec.material.model == "linear"
    extents = np.ptp(problem.nodes, axis=0)
    extent = float(extents[extents > 0].min())
    largest = np.linalg.norm(u, axis=2).max(axis=1)  # (L,)
    names = [case.name for case in problem.load_cases]
    too_far = np.flatnonzero(~(largest <= extent))  # NaN counts as too far
    if len(too_far):
        j = int(too_far[np.argmax(np.nan_to_num(largest[too_far], nan=np.inf))])
        node = int(np.nanargmax(np.linalg.norm(u[j], axis=1)))
        more = len(too_far) - 1
        others = f" (and {more} more load case{'s' if more > 1 else ''})" if more else ""
        force = float(np.linalg.norm(problem.load_cases[j].forces, axis=1).max())
        advice = (
            "the load is far too large for a linear reference: lower the forces"
            if linear
            else "the load moves the solid further than it is thick: lower the forces"
        )
        raise UnitsError(
            f"load case '{names[j]}'{others}: the {'linear' if linear else 'neo-Hookean'} FEM "
            f"reference moves node {node} by "
            f"{largest[j]:.3g} m, more than the solid's smallest extent ({extent:.3g} m): check "
            f"the units: {UNITS_HINT} (this spec: E = {problem.spec.material.youngs_modulus:g} "
            f"Pa, largest nodal force {force:.3g} N, solid {_dims(extents)} m); if they are "
            f"right, {advice}"
        )
    return [
        f"load case '{names[j]}': the largest FEM displacement, {largest[j]:.3g} m, is "
        f"{100 * largest[j] / extent:.0f}% of the solid's smallest extent ({extent:.3g} m): "
        "outside small strain: the linear reference is only approximate there and the fit "
        "inherits its error; consider smaller forces, or check E and the units "
        f"({UNITS_HINT})"
        for j in range(len(names))
        if linear and largest[j] > SMALL_STRAIN * extent
    ]


def stable_time_step(problem: Problem, stiffness: float | Any) -> float:
    """The lattice's stability estimate for the FPM step, s: ``sqrt(2 / kappa)``.

    ``kappa = max_i (sum_j k_ij) / m_i`` over the nodes that are not fixed (the derivation and
    how well it holds are in this module's docstring). Damping only raises the limit of the
    all-at-once step; the node-by-node step also needs some damping (see there).

    Args:
        problem: the problem.
        stiffness: (S,) stiffness of every spring, N/m (as
            :func:`fpm.model.stiffness.spring_stiffness` gives, stiffness_scale included), or one k
            for every spring (the spec's stiffness_scale is then applied).

    Returns:
        dt_max, s (inf if no free node has a spring).
    """
    solid = problem.solid
    k = np.asarray(stiffness, dtype=float)
    if k.ndim == 0:
        from ..model.stiffness import spring_stiffness

        k = spring_stiffness(problem, float(k))
    if k.shape != (len(solid.springs),):
        raise ValueError(
            f"stiffness has shape {k.shape}: give one value, or one per spring "
            f"({len(solid.springs)},)"
        )
    nodal = np.bincount(solid.springs.ravel(), weights=np.repeat(k, 2), minlength=problem.n_nodes)
    free = ~problem.fixed
    if not free.any():
        return float("inf")
    kappa = float((nodal[free] / solid.masses[free]).max())
    return float(np.sqrt(2.0 / kappa)) if kappa > 0 else float("inf")


def explain_rejections(
    counts: Mapping[str, int], tries: int, suggested_dt: float | None, dt: float
) -> str:
    """The message for an annealing start that found no acceptable candidate (one line).

    Args:
        counts: rejected candidates by reason: ``"diverged"``, ``"unsettled"`` (did not settle
            within max_steps), ``"no equilibrium"`` (static solve), ``"c_max"`` (cost above
            c_max); other keys are counted as given.
        tries: candidates drawn.
        suggested_dt: :func:`stable_time_step` at the stiffest candidate (the top of the k
            bounds), s, or None if unknown.
        dt: the spec's time step, s.
    """
    labels = {
        "diverged": "diverged",
        "unsettled": "did not settle within max_steps",
        "no equilibrium": "had no static equilibrium",
        "c_max": "cost more than c_max",
    }
    seen = [key for key in (*REJECTIONS, *sorted(set(counts) - set(REJECTIONS))) if counts.get(key)]
    tally = ", ".join(f"{counts[key]} {labels.get(key, key)}" for key in seen) or "none counted"
    advice = []
    if counts.get("diverged"):
        if suggested_dt is None:
            advice.append(
                "for divergence: lower fpm.dt, or raise the low end of annealing.bounds.d"
            )
        else:
            estimate = (
                f"the lattice's stability estimate suggests dt <= {suggested_dt:.3g} s "
                f"(the spec has {dt:.3g} s)"
            )
            if dt > suggested_dt:
                advice.append(
                    f"for divergence: {estimate}: lower fpm.dt, or lower the top of "
                    "annealing.bounds.k"
                )
            else:
                advice.append(
                    f"for divergence: {estimate}, so the time step is not the cause: the "
                    "divergent candidates are under-damped (the node-by-node step needs some "
                    "damping at any dt): raise the low end of annealing.bounds.d"
                )
    if counts.get("unsettled"):
        advice.append(
            "for not settling: raise fpm.max_steps, or move annealing.bounds.d (a run that "
            "creeps needs less damping, one that rings needs more)"
        )
    if counts.get("no equilibrium"):
        advice.append(
            "for no equilibrium: check that the fixed nodes hold the solid, or narrow "
            "annealing.bounds.k"
        )
    if counts.get("c_max"):
        advice.append(
            "for cost above c_max: the FEM reference may be wrong (check its units and fixed "
            "nodes with `fpmcal fem`), or the fit lies outside annealing.bounds.k: widen the "
            "bounds, or raise annealing.c_max"
        )
    return f"no acceptable starting point in {tries} random tries: {tally}" + "".join(
        f"; {a}" for a in advice
    )


def _dims(extents: np.ndarray) -> str:
    return " x ".join(f"{float(e):.3g}" for e in extents)
