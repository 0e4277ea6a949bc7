"""Calibration: fit the FPM's stiffness, d and depth to the FEM reference (paper Sec. 4.2-4.4).

Two methods (``annealing.method``; docs/physics.md):

- ``two-stage`` (the default). Stage 1: simulated annealing over the stiffness parameters only
  (k, or one k per spring family), each candidate's cost Eq. (2) taken at its static
  equilibrium (:class:`fpm.fitting.cost.StaticCost`; the settled state does not depend on d); then a
  bounded local polish from the best state (:func:`fpm.fitting.stiffness_stage.polish`). Stage 2:
  d, the value that settles every load case in the fewest total steps at the spec's dt
  (:mod:`fpm.fitting.damping.search`).
- ``paper``: simulated annealing over (stiffness, d) jointly, every candidate run dynamically
  to rest (:class:`fpm.fitting.cost.CostFunction`); among the states within 0.1% of the best
  cost the fastest-settling wins (:func:`pick_paper_state`).

Either way, depth 'auto' is resolved on static equilibria (:func:`resolve_depth`) and a last
dynamic run at (stiffness, d, depth) gives the reported cost, discrepancies and settle steps,
and :func:`fpm.fitting.verdict.judge` the verdict on the fit (good, fair or poor, and why).

Data flow (the service runs each step as a job): :func:`check_reference` (units) ->
:func:`run_chain` (one seeded chain; families+volume chains share one first reduced basis,
:func:`fpm.fitting.reduced.first_basis`, which needs no reference) -> :func:`fit_stage`
(two-stage: polish, depth, d) -> :func:`finalize` -> :class:`CalibrationResult`.
:func:`calibrate` does all of it in-process, the same way.

This module is the orchestration (calibrate, finalize, the paper method's pick); the steps live
beside it, and their entry points and results are importable from here (``__all__``):

- :mod:`fpm.fitting.bounds`: the search box (stiffness, d, depth) and the note on kappa's floor;
- :mod:`fpm.fitting.stiffness_stage`: stage 1, :func:`run_chain` (:class:`ChainResult`), the
  linear estimate, the polish;
- :mod:`fpm.fitting.damping.stage`: stage 2, :func:`fit_stage` (:class:`DampingStage`): the
  polish, :func:`resolve_depth`, d (:func:`fpm.fitting.damping.choice.fit_damping`);
- :mod:`fpm.fitting.reference`: the reference's parts, its checks (:func:`check_reference`);
- :mod:`fpm.fitting.damping.validation`: the last dynamic run's check, the validation cases;
- below them: cost, annealing, reduced (families+volume's stage 1), damping (the d search).

Defaults:
- cost is normalised by the reference cost (the cost of an FPM that does not move), so
  temperatures and c_max are scale-free;
- k bounds (each family): [E h / 100, 10 E h]; d bounds: [0.1, 5] sqrt(E h m), m the mean node
  mass (:mod:`fpm.fitting.bounds`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ..dynamics.step_caps import fixed_max_steps
from ..model import materials
from ..model.problem import Problem
from ..model.stiffness import has_volume, stiffness_dict, volume_stiffness
from .bounds import fit_depth, full_depth, mode_notes
from .cost import CostFunction, StaticCost, dynamic_time_step
from .damping.depth import resolve_depth
from .damping.stage import DampingStage, fit_stage
from .damping.validation import FinalRun, Validation, final_run, validate
from .field import field_parts
from .reduced import first_basis
from .reference import check_reference, reference_displacements
from .result import (
    CalibrationResult,
    ChainSummary,
    FitFigures,
    ModelParameters,
    ReferenceFacts,
    RunFacts,
    SettleFigures,
)
from .step_budget import budget_notes
from .stiffness_stage import ChainResult, Progress, run_chain
from .verdict import judge

__all__ = [
    # the orchestration
    "calibrate",
    "finalize",
    "pick_paper_state",
    # the stage entry points the worker calls, and their results
    "check_reference",
    "run_chain",
    "ChainResult",
    "fit_stage",
    "DampingStage",
    "Progress",
]

EQUALLY_GOOD = 0.001
"""Paper method: states within this fraction of the best cost are equally good; the
fastest-settling wins."""
SAME_SPEED = 0.05
"""Paper method: settle step counts within this fraction of the fewest are equally fast."""


def pick_paper_state(chains: list[ChainResult]) -> tuple[list[float], float]:
    """Paper method: among the states within 0.1% of the best cost over every chain, the one
    that settles in the fewest total steps (counts within 5% are equally fast, and then the
    cheapest wins). Returns (stiffness parameters, d)."""
    best_cost = min(c.cost for c in chains)
    candidates = [
        s for c in chains for s in c.near_best if s.cost <= best_cost * (1 + EQUALLY_GOOD)
    ]
    if any(s.settled for s in candidates):
        candidates = [s for s in candidates if s.settled]
    fewest = min(sum(s.steps or ()) for s in candidates)
    fast = [s for s in candidates if sum(s.steps or ()) <= fewest * (1 + SAME_SPEED)]
    pick = min(fast, key=lambda s: (s.cost, sum(s.steps or ())))
    return list(pick.x[:-1]), float(pick.x[-1])


def unseen_note(problem: Problem) -> list[str]:
    """A note when a calibration of several stiffness parameters has no validation cases: its
    figures are then all on the loads it was fitted to, which flatter it. The paper's model (one
    k: ``fpm.stiffness`` ``"single"``) or method, which judge their fit on its own loads as the
    paper does, get none (one k has little room to flatter itself)."""
    paper = problem.spec.fpm.stiffness == "single" or problem.spec.annealing.method == "paper"
    if problem.validation_cases or paper:
        return []
    return [
        "no validation cases: every figure here is on the loads the fit was chosen for, which "
        "flatter it; name a few loads it never sees as validation_cases to learn how it does "
        "elsewhere (docs/howto/validation-cases.md)"
    ]


def finalize(
    problem: Problem,
    reference: Any,
    chains: list[ChainResult],
    damping: DampingStage | None = None,
    *,
    warnings: list[str] | None = None,
) -> CalibrationResult:
    """The calibration result: a last dynamic run at (stiffness, d, depth) and its figures.

    Two-stage needs ``damping`` (from :func:`fit_stage`); the paper method picks its state
    from the chains and resolves depth 'auto' on static equilibria.
    """
    if not chains:
        raise ValueError("no chain results")
    t0 = time.perf_counter()
    disp = reference_displacements(reference, problem)
    method = chains[0].method
    if method == "two-stage":
        if damping is None:
            raise ValueError("the two-stage method needs the damping stage's result")
        theta, d, depth, deepest = damping.theta, damping.d, damping.depth, damping.full_depth
        final = damping.final
    else:
        static = StaticCost(problem, disp, None)
        theta, d = pick_paper_state(chains)
        deepest = full_depth(problem)
        if problem.spec.fpm.depth == "auto":
            depth, deepest, _ = resolve_depth(static, theta, problem.spec.fpm.auto_depth_tolerance)
        else:
            asked = fit_depth(problem)
            depth = deepest if asked is None else asked
        dynamic = CostFunction(problem, disp, depth)
        runs = [dynamic.displacements(theta, d, j) for j in range(len(problem.load_cases))]
        final = final_run(
            static,
            theta,
            depth,
            np.stack([r.displacements for r in runs]),
            [r.steps for r in runs],
            all(r.settled for r in runs),
        )
    settle = _settle_figures(problem, final, damping)
    # Full depth reaches every node from any load (a validation load elsewhere needs it).
    checked = None if depth >= deepest else depth
    field, model, field_notes = field_parts(problem, reference, damping, theta, checked)
    m = problem.solid.masses
    parameters = ModelParameters(
        stiffness_mode=problem.spec.fpm.stiffness,
        loads=problem.loads,
        k=float(theta[0]),
        stiffness=stiffness_dict(problem, theta),
        volume_stiffness=volume_stiffness(problem, theta),
        regions=materials.report(problem, theta),
        d=float(d),
        depth=int(depth),
        full_depth=int(deepest),
        step_budget=None if damping is None else damping.step_budget,
        h=problem.h,
        node_mass={
            "min": float(m.min()),
            "max": float(m.max()),
            "mean": float(m.mean()),
            "total": float(m.sum()),
        },
        field=field,
    )
    saved = None if damping is None else damping.validation
    if saved is not None and saved["depth"] == checked:  # solved beside the damping stage
        validation = Validation(
            saved["relative"], saved["h_percent"], saved["notes"], saved.get("compliance", [])
        )
    else:
        validation = validate(problem, reference, model, checked)
    fit = FitFigures(
        cost=final.cost,
        static_cost=final.static_cost,
        relative_discrepancy=final.relative,
        loaded_discrepancy=final.loaded,
        discrepancy_h=final.h_percent,
        validation_cases=[c.name for c in problem.validation_cases],
        validation_relative_discrepancy=validation.relative,
        validation_discrepancy_h=validation.h_percent,
        compliance_ratio=final.compliance,
        validation_compliance_ratio=validation.compliance,
    )
    result = CalibrationResult(
        method=method,
        parameters=parameters,
        fit=fit,
        settle=settle,
        reference=_reference_facts(problem, reference),
        run=_run_facts(chains, damping, time.perf_counter() - t0),
        warnings=list(warnings or [])
        + problem.warnings
        + final.notes
        + validation.notes
        + unseen_note(problem)
        + mode_notes(problem)
        + field_notes
        + budget_notes(None if damping is None else damping.step_budget)
        + unfitted_notes(damping),
    )
    result.fit.verdict = judge(problem, result, theta, reference)
    return result


def unfitted_notes(damping: DampingStage | None) -> list[str]:
    """The warning of a damping stage that fitted no d (:attr:`DampingStage.unfitted`)."""
    if damping is None or damping.unfitted is None:
        return []
    return [
        f"damping not fitted: {damping.unfitted}. The stiffness and every figure stand (they "
        f"are static equilibria); d = {damping.d:.4g} N s/m is an estimate (the modes' "
        "prediction, else the critical damping), not checked by a run, so this kernel may "
        "settle slowly at it; an engine steps at the export's engine d and dt "
        "(parameters.engine), which do not depend on it"
    ]


def _settle_figures(
    problem: Problem, final: FinalRun, damping: DampingStage | None
) -> SettleFigures:
    """How the last dynamic run settled (``final``), with the damping stage's time step, step
    cap, d bounds and settle criterion (None: the paper method, whose time step and step cap
    are the spec's)."""
    return SettleFigures(
        dt=damping.dt if damping is not None else dynamic_time_step(problem),
        max_steps=fixed_max_steps(problem.spec.fpm.max_steps)
        if damping is None or damping.max_steps is None
        else damping.max_steps,
        steps=final.settle_steps,
        settled=final.settled,
        d_min=None if damping is None else damping.d_min,
        d_predicted=None if damping is None else damping.d_predicted,
        stiffness=None if damping is None else damping.settle,
        distance=final.settle_distance,
        distance_estimated=final.settle_estimated,
        distance_measured=final.settle_measured,
    )


def _reference_facts(problem: Problem, reference: Any) -> ReferenceFacts:
    """What the fit was measured against: the spec's reference label and, for a FEM
    reference (:class:`fpm.fem.solution.FemResult`), its estimated error per load case and
    per validation case, % ((L + V,) split at L), and its refinements."""
    from ..fem.reference import reference_label

    n_cases = len(problem.load_cases)
    fem_error = getattr(reference, "estimated_error", None)
    return ReferenceFacts(
        label=reference_label(problem.spec),
        error=None if fem_error is None else fem_error[:n_cases],
        validation_error=None if fem_error is None else fem_error[n_cases:],
        refinements=getattr(reference, "refinements", None),
    )


def _run_facts(
    chains: list[ChainResult], damping: DampingStage | None, finalize_seconds: float
) -> RunFacts:
    """What the calibration took: evaluations and runs over the chains and the damping stage
    (None: the paper method), the wall time per stage, s (the chains' slowest for stage 1;
    ``finalize_seconds`` for finalize), the winning chain's cost history and each chain's
    outcome."""
    winner = min(chains, key=lambda c: c.cost)
    return RunFacts(
        evaluations=sum(c.evaluations for c in chains)
        + (damping.polish_evaluations if damping else 0),
        damping_runs=damping.damping_runs if damping else 0,
        seconds={
            "stiffness": max(c.seconds for c in chains),
            "damping": damping.seconds if damping else 0.0,
            "finalize": finalize_seconds,
        },
        history=winner.history,
        chains=[
            ChainSummary(chain=c.chain, x=c.x, cost=c.cost, evaluations=c.evaluations)
            for c in chains
        ],
    )


def calibrate(
    problem: Problem,
    *,
    chains: int | None = None,
    progress: Progress | None = None,
    reference: Any = None,
    threads: int | None = None,
    stored_chains: list[ChainResult] | None = None,
    keep_chains: Callable[[list[ChainResult]], None] | None = None,
) -> CalibrationResult:
    """Fit stiffness, d and depth for ``problem`` in-process.

    Args:
        problem: from :func:`fpm.load_problem`.
        chains: number of annealing chains (None = the spec's).
        progress: called with {phase, chain, move, moves, temperature, best_cost, ...};
            phases fem, annealing, polish, depth, damping, finalize.
        reference: FEM result or (L, N, 3) displacements (None = the spec's
            ``reference.displacements`` if given, else solve the FEM now).
        threads: chains run at once (None = one per core).
        stored_chains: stage 1's chain results from an earlier run of the same problem and
            reference (e.g. ``fpmcal calibrate``'s cache): no annealing, the stages after it
            start from them.
        keep_chains: given stage 1's chain results as soon as they are found, before the
            stages after it start (so a later failure does not lose them).

    Raises:
        fpm.fitting.diagnosis.UnitsError: the FEM reference moves more than the solid's smallest
            extent (almost always a units mistake), before any annealing.
        AnnealingError: the search cannot start (with what to change).
    """
    n = problem.spec.annealing.chains if chains is None else chains
    if n < 1:
        raise ValueError("chains must be >= 1")
    if reference is None:
        from ..fem.reference import reference_for

        if progress is not None:
            progress({"phase": "fem"})
        reference = reference_for(problem)
    warnings = check_reference(problem, reference)
    two_stage = problem.spec.annealing.method == "two-stage"
    # families+volume: the chains' first reduced basis, built once for all of them
    basis = first_basis(problem) if two_stage and has_volume(problem) else None

    def one(chain: int) -> ChainResult:
        cb = None if progress is None else (lambda info: progress({"phase": "annealing", **info}))
        return run_chain(problem, reference, chain, progress=cb, basis=basis)

    workers = min(n, threads or os.cpu_count() or 1)
    if stored_chains is not None:
        if len(stored_chains) != n:
            raise ValueError(f"stored_chains: {len(stored_chains)} chain results for {n} chains")
        results = list(stored_chains)
    elif workers == 1:
        results = [one(c) for c in range(n)]
    else:
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(one, range(n)))
    if keep_chains is not None and stored_chains is None:
        keep_chains(results)
    damping = None
    if two_stage:
        damping = fit_stage(problem, reference, results, progress=progress, basis=basis)
    if progress is not None:
        progress({"phase": "finalize"})
    return finalize(problem, reference, results, damping, warnings=warnings)
