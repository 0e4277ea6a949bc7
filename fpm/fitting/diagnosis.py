"""Diagnoses for the user: a reference in the wrong units, and why an annealing start failed.
Every message says what to change.

The lattice's stability estimate lives in :mod:`fpm.dynamics.stability`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..model.problem import Problem
from ..model.spec import UNITS_HINT

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
