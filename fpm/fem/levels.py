"""The levels of a refined reference (:mod:`fpm.fem.refine`): meshes solved one refinement finer
at a time until they agree, and the estimated error, the relative change at the lattice nodes
from the last level to the one before (:func:`relative_change`), in %.

:func:`converge` solves the levels ``reference.refine`` asks for (n: levels n - 1 and n;
``"auto"``: until the change is below :data:`TOLERANCE` or the node budget stops it),
:func:`summarise` hands back the last with its estimate and every level's figures, and
:func:`checked` estimates the error of a reference as given against one refinement
(``refine: "check"``). Each level is a :class:`Mesh`, which knows how to solve itself and how to
make the next; the meshes themselves are :mod:`fpm.fem.uniform_refinement`'s.

Units: m, N; changes in %.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .solution import FemError, FemResult

TOLERANCE = 1.0
"""``refine: "auto"`` stops when the change between two levels is below this, %, in every case."""
WARN_ERROR = 5.0
"""A calibration warns about a load case whose reference's estimated error is above this, %."""
DEFAULT_NODE_BUDGET = 400_000
"""``reference.node_budget`` when not given: a refined level has at most this many FEM nodes."""
WORK_ITERATIONS = 100
"""``refine: "auto"`` also stops before a level whose predicted work, its FEM nodes times the
CG iterations per case the level before needed (refinement does not lower them), is over
``reference.node_budget`` times this: about what a well-shaped mesh needs, where one of
slivers needs many times as many."""

__all__ = [
    "DEFAULT_NODE_BUDGET",
    "TOLERANCE",
    "WARN_ERROR",
    "WORK_ITERATIONS",
    "converge",
    "relative_change",
]


def relative_change(coarse: np.ndarray, fine: np.ndarray) -> list[float]:
    """Per load case, ``100 sum_i |u_fine - u_coarse| / sum_i |u_fine|`` over the nodes, %
    (``coarse``, ``fine``: (L, N, 3) displacements at the lattice nodes, m)."""
    diff = np.linalg.norm(fine - coarse, axis=2).sum(axis=1)
    scale = np.linalg.norm(fine, axis=2).sum(axis=1)
    return [float(100 * d / s) if s > 0 else 0.0 for d, s in zip(diff, scale, strict=True)]


Progress = Callable[[dict[str, Any]], None]
"""Told each level of a refined reference as it starts (:func:`converge`)."""


@dataclass
class Level:
    """One solve of the reference.

    Attributes:
        refinements: uniform refinements of the given mesh (0: as given).
        fem_nodes: the FEM's nodes at this level.
        result: its :class:`FemResult` on the lattice.
        seconds: wall time of this level (mesh, loads, assembly and solve), s.
    """

    refinements: int
    fem_nodes: int
    result: FemResult
    seconds: float


@dataclass
class Mesh:
    """A level's mesh before it is solved: its FEM node count and how to solve it."""

    refinements: int
    fem_nodes: int
    solve: Callable[[], FemResult]
    finer: Callable[[], Mesh]


def converge(
    first: Mesh,
    refine: int | str,
    budget: int,
    *,
    tolerance: float = TOLERANCE,
    progress: Progress | None = None,
) -> tuple[list[Level], list[str]]:
    """Solve the levels ``refine`` asks for, starting from the mesh ``first`` (level 0).

    ``refine`` n >= 1: levels n - 1 and n; ``"auto"``: 0, 1, ... until the change is below
    ``tolerance`` (%) in every case or the next level has more than ``budget`` FEM nodes or
    more predicted work than ``budget`` times :data:`WORK_ITERATIONS` (its FEM nodes times
    the most CG iterations a case of the level before needed).
    ``progress`` is told each level as it starts: ``{"level": refinements, "fem_nodes": n,
    "last_change": the largest change so far (%, None before two levels)}``.
    Returns the levels solved and notes (a level refused by the budget).
    """
    notes: list[str] = []
    mesh = first
    if isinstance(refine, int):
        for _ in range(max(0, refine - 1)):
            mesh = mesh.finer()
            _within(mesh, budget)  # before any solve: the spec asks for more than it allows
    levels: list[Level] = []
    last: float | None = None
    while True:
        if mesh.fem_nodes > budget and mesh.refinements > 0:  # the mesh as given always runs
            if not isinstance(refine, int) and levels:
                notes.append(
                    f"reference.refine: stopped at {levels[-1].refinements} refinement(s): the "
                    f"next would have {mesh.fem_nodes:,} FEM nodes, over reference.node_budget "
                    f"({budget:,})"
                )
                break
            _within(mesh, budget)
        iterations = max(levels[-1].result.iterations, default=0) if levels else 0
        if not isinstance(refine, int) and mesh.fem_nodes * iterations > budget * WORK_ITERATIONS:
            notes.append(
                f"reference.refine: stopped at {levels[-1].refinements} refinement(s): the next "
                f"would have {mesh.fem_nodes:,} FEM nodes, and at the {iterations:,} CG "
                f"iterations per case this level needed (a well-shaped mesh needs about "
                f"{WORK_ITERATIONS}; slivers need more) it would cost as much as "
                f"{mesh.fem_nodes * iterations // WORK_ITERATIONS:,} nodes, over "
                f"reference.node_budget ({budget:,}): improve the mesh's worst tetrahedra, or "
                "raise reference.node_budget"
            )
            break
        if progress is not None:
            progress({"level": mesh.refinements, "fem_nodes": mesh.fem_nodes, "last_change": last})
        t0 = time.perf_counter()
        result = mesh.solve()
        levels.append(Level(mesh.refinements, mesh.fem_nodes, result, time.perf_counter() - t0))
        if isinstance(refine, int):
            if mesh.refinements >= refine:
                break
        elif len(levels) >= 2:
            change = relative_change(levels[-2].result.displacements, result.displacements)
            last = max(change, default=0.0)
            if last < tolerance:
                break
        mesh = mesh.finer()
    return levels, notes


def _within(mesh: Mesh, budget: int) -> None:
    """Raise when a level the spec names has more FEM nodes than the budget."""
    if mesh.fem_nodes > budget:
        raise FemError(
            f"reference.refine: {mesh.refinements} refinement(s) make {mesh.fem_nodes:,} FEM "
            f"nodes, over reference.node_budget ({budget:,}): ask for fewer, or 'auto', or raise "
            "reference.node_budget"
        )


def summarise(levels: list[Level], notes: list[str]) -> FemResult:
    """The last level's result, with the estimated error (its change from the level before)
    and every level's figures."""
    last = levels[-1].result
    table: list[dict[str, Any]] = []
    for i, level in enumerate(levels):
        change = (
            relative_change(levels[i - 1].result.displacements, level.result.displacements)
            if i
            else None
        )
        table.append(
            {
                "refinements": level.refinements,
                "fem_nodes": level.fem_nodes,
                "change": change,
                "seconds": round(level.seconds, 3),
                "iterations": list(level.result.iterations),
            }
        )
    error = table[-1]["change"]
    if error is None:
        notes = [*notes, "reference.refine: one level only, so its error is not estimated"]
    return replace(
        last,
        estimated_error=error,
        refinements=levels[-1].refinements,
        levels=table,
        loads="spread",
        notes=list(last.notes) + notes,
    )


def checked(
    base: FemResult,
    base_nodes: int,
    refined: Callable[[], Mesh],
    budget: int,
    limit: int | None,
) -> FemResult:
    """``base`` (the reference as given, ``base_nodes`` FEM nodes) with its error estimated
    against one refinement with spread loads (``refined``), unless that has more FEM nodes than
    ``budget`` (or ``limit``)."""
    cap = budget if limit is None else min(budget, limit)
    finer = refined() if 4 * base_nodes <= cap else None  # a refined mesh has ~8x the nodes
    if finer is None or finer.fem_nodes > cap:
        if limit is not None:  # the default check, on a lattice too large for it: no estimate
            return base
        size = f"{finer.fem_nodes:,}" if finer is not None else f"about {8 * base_nodes:,}"
        why = (
            f"reference.refine 'check': not run, its refined mesh would have {size} FEM nodes, "
            f"over reference.node_budget ({cap:,}); the reference's error is not estimated"
        )
        return replace(base, notes=[*base.notes, why])
    t0 = time.perf_counter()
    check = finer.solve()
    seconds = time.perf_counter() - t0
    error = relative_change(base.displacements, check.displacements)
    table: list[dict[str, Any]] = [
        {"refinements": 0, "fem_nodes": base_nodes, "change": None, "loads": "nodal"},
        {
            "refinements": 1,
            "fem_nodes": finer.fem_nodes,
            "change": error,
            "seconds": round(seconds, 3),
            "loads": "spread",
        },
    ]
    return replace(base, estimated_error=error, refinements=0, levels=table)
