"""Diagnoses for the user: a reference in the wrong units or under too large a load, and why an
annealing start failed. Every message says what to change.

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
    """The FEM reference moves a node further than the solid is thick: the units are wrong, or
    the load is far too large for the reference."""


SOFTEST = 100.0
"""Pa: a Young's modulus below this is softer than any tissue (brain, fat: about 0.5-3 kPa),
so most likely written in kPa (E = 5 for 5 kPa)."""
LARGEST = 2.0
"""m: a solid larger than this across is most likely a mesh in mm or cm read as m."""


def check_reference(problem: Problem, displacements: Any) -> list[str]:
    """Check that the FEM reference is plausible; return warnings (one line each).

    Args:
        problem: the problem.
        displacements: (L, N, 3) or (L + V, N, 3) FEM displacements, m: the load cases, then
            (if given) the validation cases (or a :class:`fpm.fem.reference.FemResult`).

    Returns:
        For the linear model, one warning per load or validation case whose largest nodal
        displacement is above 10% of the solid's smallest bounding-box extent (outside small
        strain, where a linear reference is only approximate); none for the neo-Hookean model,
        which is made for large deformation.

    Raises:
        UnitsError: a case moves a node further than the smallest extent: the message names
            the case and the spec's values that look like a units mistake (E below
            :data:`SOFTEST`, a solid over :data:`LARGEST` across), if any; otherwise it says
            that the load is far too large (the linear reference is meaningless there).
        ValueError: ``displacements`` holds neither L nor L + V cases.
    """
    u = np.asarray(getattr(displacements, "displacements", displacements), dtype=float)
    cases, names = _cases(problem, len(u))
    linear = problem.spec.material.model == "linear"
    extents = np.ptp(problem.nodes, axis=0)
    extent = float(extents[extents > 0].min())
    largest = np.linalg.norm(u, axis=2).max(axis=1)  # (cases,)
    suspects = _unit_suspects(problem, extents)
    too_far = np.flatnonzero(~(largest <= extent))  # NaN counts as too far
    if len(too_far):
        j = int(too_far[np.argmax(np.nan_to_num(largest[too_far], nan=np.inf))])
        node = int(np.nanargmax(np.linalg.norm(u[j], axis=1)))
        more = len(too_far) - 1
        others = f" (and {more} more case{'s' if more > 1 else ''})" if more else ""
        force = float(np.linalg.norm(cases[j].forces, axis=1).max())
        given = (
            f"this spec: E = {problem.spec.material.youngs_modulus:g} Pa, largest nodal force "
            f"{force:.3g} N, solid {_dims(extents)} m"
        )
        moved = (
            f"{names[j]}{others}: the {'linear' if linear else 'neo-Hookean'} FEM reference "
            f"moves node {node} by {largest[j]:.3g} m, more than the solid's smallest extent "
            f"({extent:.3g} m)"
        )
        too_large = (
            "the load is far too large for a linear reference: lower the forces"
            if linear
            else "the load moves the solid further than it is thick: lower the forces"
        )
        if suspects:
            raise UnitsError(
                f"{moved}: check the units ({UNITS_HINT}): {'; '.join(suspects)} ({given}); if "
                f"they are right, {too_large}"
            )
        raise UnitsError(f"{moved}: {too_large} ({given})")
    units = f", or check the units ({UNITS_HINT}: {'; '.join(suspects)})" if suspects else ""
    return [
        f"{names[j]}: the largest FEM displacement, {largest[j]:.3g} m, is "
        f"{100 * largest[j] / extent:.0f}% of the solid's smallest extent ({extent:.3g} m): "
        "outside small strain: the linear reference is only approximate there and the fit "
        f"inherits its error; consider smaller forces{units}"
        for j in range(len(names))
        if linear and largest[j] > SMALL_STRAIN * extent
    ]


def _cases(problem: Problem, count: int) -> tuple[list[Any], list[str]]:
    """The cases of a reference of ``count`` cases (the load cases, or those then the
    validation cases) and how messages name them."""
    loads, unseen = problem.load_cases, problem.validation_cases
    if count not in (len(loads), len(loads) + len(unseen)):
        raise ValueError(
            f"the FEM reference holds {count} cases where the spec has {len(loads)} load cases"
            + (f" and {len(unseen)} validation cases" if unseen else "")
        )
    cases = (loads + unseen)[:count]
    names = [f"load case '{c.name}'" for c in loads] + [
        f"validation case '{c.name}'" for c in unseen
    ]
    return cases, names[:count]


def _unit_suspects(problem: Problem, extents: np.ndarray) -> list[str]:
    """What in the spec looks like a value in another unit (empty: nothing does)."""
    out = []
    e = problem.spec.material.youngs_modulus
    if e < SOFTEST:
        out.append(f"E = {e:g} Pa is softer than any tissue (5 kPa is 5000)")
    if float(extents.max()) > LARGEST:
        out.append(
            f"the solid is {float(extents.max()):.3g} m across (a mesh in mm is read with "
            "--scale 0.001)"
        )
    return out


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
