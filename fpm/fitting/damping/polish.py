"""The polish of stage 2: the chains' best stiffness theta (N/m; kappa Pa) polished on static
equilibria at the depth the chains fitted at."""

from __future__ import annotations

import numpy as np

from ...dynamics.eigen import single_threaded_blas
from ...dynamics.modes_ahead import ModesAhead
from ...dynamics.stability import stable_time_step
from ...model.problem import Problem
from ...model.stiffness import has_volume, is_extended, model_stiffness
from ..bounds import stiffness_bounds
from ..cost import StaticCost
from ..defect_correction import fit_reduced
from ..reduced import ReducedBasis, first_basis
from ..stiffness_stage import (
    POLISH_SPAN,
    UNIFORM_SPAN,
    ChainResult,
    Progress,
    constrained_cost,
    polish,
)
from .settings import DEFAULT, DampingSettings


def chain_to_polish(
    problem: Problem, chains: list[ChainResult], settings: DampingSettings = DEFAULT
) -> ChainResult:
    """The chain whose best state stage 2 takes: the cheapest; with material regions or
    anisotropy, among those within ``settings.same_fit`` of it, the one with the longest time
    step (a region the loads barely strain lets its parameters drift up at no cost, and a
    drifted kappa shortens dt several times)."""
    best = min(chains, key=lambda c: c.cost)
    if not is_extended(problem):
        return best
    near = [c for c in chains if c.cost <= best.cost * (1 + settings.same_fit)]
    return max(near, key=lambda c: stable_time_step(problem, model_stiffness(problem, c.x)))


def polish_stiffness(
    problem: Problem,
    cost: StaticCost,
    start: list[float],
    progress: Progress | None,
    basis: ReducedBasis | None,
    ahead: ModesAhead,
) -> tuple[list[float], int]:
    """The polished stiffness theta from the chosen chain's best ``start``, and the static
    solves made beside ``cost``'s evaluations. families+volume (and field): the
    defect-corrected reduced fit on ``basis`` (built when None), which starts ``ahead`` after
    its rounds; otherwise :func:`_polish`."""
    if progress is not None:
        progress({"phase": "polish"})
    bounds = stiffness_bounds(problem)
    if has_volume(problem):  # the defect-corrected reduced fit is the polish
        with single_threaded_blas():
            theta, _, solves = fit_reduced(
                cost, basis or first_basis(problem), start, bounds, progress,
                after_round=ahead.start,
            )  # fmt: skip
        problem.cache.reduced_units = None  # its unit matrices are not needed again
        return theta, solves
    return _polish(cost, start, bounds, progress), 0


def _polish(
    cost: StaticCost,
    start: list[float],
    bounds: tuple[np.ndarray, np.ndarray],
    progress: Progress | None,
) -> list[float]:
    """The polished stiffness from the chains' best ``start`` (not families+volume): with
    families, from the better of it and the best single k, under that k's case costs as
    ceilings."""
    ceilings = None
    if len(start) > 1:
        uniform, _ = polish(
            cost, [float(np.exp(np.mean(np.log(start))))], (bounds[0][:1], bounds[1][:1]),
            progress, span=UNIFORM_SPAN, uniform=len(start),
        )  # fmt: skip
        ceilings = cost(uniform * len(start)).case_costs
        chains_best = constrained_cost(cost(start), cost.reference_cost, ceilings)
        if constrained_cost(cost(uniform * len(start)), cost.reference_cost, None) < chains_best:
            start = uniform * len(start)
    span = UNIFORM_SPAN if len(start) > 1 else POLISH_SPAN
    theta, _ = polish(cost, start, bounds, progress, span=span, ceilings=ceilings)
    return list(theta)
