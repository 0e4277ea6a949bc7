"""The FEM reference as the fit reads it: a :class:`fpm.fem.reference.FemResult` or an array
of displacements, m, holding the load cases' (L, N, 3) in spec order, then the validation
cases' (V, N, 3) when it was solved for them; and its checks before any annealing (units,
resolution)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..model.problem import Problem


def reference_displacements(reference: Any, problem: Problem | None = None) -> np.ndarray:
    """(L, N, 3) from a FemResult (``.displacements``) or an array: the load cases' part
    (the reference also holds the validation cases after them, :func:`validation_reference`)."""
    every = np.asarray(getattr(reference, "displacements", reference), dtype=float)
    return every if problem is None else every[: len(problem.load_cases)]


def validation_reference(reference: Any, problem: Problem) -> np.ndarray | None:
    """(V, N, 3) the reference of the validation cases, or None if it holds none (a reference
    of the load cases only)."""
    every = np.asarray(getattr(reference, "displacements", reference), dtype=float)
    n, v = len(problem.load_cases), len(problem.validation_cases)
    if not v or len(every) < n + v:
        return None
    return every[n : n + v]


def check_reference(problem: Problem, reference: Any) -> list[str]:
    """Units sanity of the FEM reference, load and validation cases
    (:func:`fpm.fitting.diagnosis.check_reference`): raises on a reference no small-strain
    solid gives, returns warnings."""
    from .diagnosis import check_reference as check

    return check(problem, reference) + resolution_notes(problem, reference)


def resolution_notes(problem: Problem, reference: Any) -> list[str]:
    """Warnings on how far the reference is from converged (:mod:`fpm.fem.refine`): a load or
    validation case whose estimated error is above WARN_ERROR, and the reference's own notes
    (a refinement the node budget refused, an error not estimated)."""
    from ..fem.levels import WARN_ERROR

    error = getattr(reference, "estimated_error", None)
    notes = [str(n) for n in getattr(reference, "notes", None) or []]
    if error is None:
        return notes
    names = [c.name for c in problem.load_cases] + [
        f"{c.name} (validation)" for c in problem.validation_cases
    ]
    refined = int(getattr(reference, "refinements", 0) or 0)
    how = (
        f"the change from its last refinement ({refined} in all)"
        if refined
        else "its change under one refinement with the force spread over the node's share of "
        "the solid"
    )
    return [
        f"load case '{name}': the reference's estimated error is {e:.1f}% ({how}), above "
        f"{WARN_ERROR:g}%: the reference does not resolve this load (a force on a single node "
        "of a coarse mesh, a press on one voxel); the fit inherits that error: use "
        "reference.refine 'auto' (or a higher number, or a larger reference.node_budget), or "
        'spread the force over more nodes ("distribute": true)'
        for name, e in zip(names, error, strict=False)
        if e > WARN_ERROR
    ] + notes
