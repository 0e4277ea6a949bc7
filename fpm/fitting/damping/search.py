"""The d search: the d in the bounds that settles every load case in the fewest total steps,
with the real dynamic kernel (:class:`fpm.dynamics.simulation.FpmModel`).

From the predicted d (:mod:`fpm.dynamics.modes`) it confirms with a run on either side, walks
on only where one is faster and refines by golden section; without a prediction it brackets
from two critical-damping estimates. A d is dropped once its steps, or its runs' decays,
say it cannot win (:mod:`fpm.fitting.damping.lockstep`); every figure returned comes from runs
that settled. How and why: docs/explanation/physics/damping-search.md."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...dynamics.modes import Prediction, total_steps
from ...dynamics.reduced_step import StepModel
from ...dynamics.simulation import DynamicRun
from ...dynamics.stability import time_step
from ...dynamics.step_caps import AUTO_CEILING, FALLBACK_STEPS, SCHEMA_MAX_STEPS
from ...dynamics.voigt import SETTLED
from ...model.forces import Stiffness
from ...model.problem import Problem
from .lockstep import (
    CaseRun,
    Request,
    Spread,
    _Runs,
)
from .margin import predicted_edge, smallest_settling
from .settings import DEFAULT, DampingSettings
from .unsettled import DampingError, Hopeless, ShortCap, hopeless, long_decay, what_would_work

GOLDEN = (3 - math.sqrt(5)) / 2
"""Golden-section fraction: where in the wider gap the next d goes."""


@dataclass
class DampingFit:
    """The fastest-settling d for a fitted stiffness.

    Attributes:
        d: nodal damping, N s/m.
        steps: (L,) time steps each load case takes to settle at d.
        displacements: (L, N, 3) the settled displacements at d, m.
        d_min: smallest d found that settles every load case within ``margin_cap`` times its
            steps at d, N s/m (to a factor of about 1.12; the lower bound if that settles).
        guess: where the search started, N s/m: the predicted d, or the geometric mean of the
            two critical-damping estimates.
        runs: dynamic runs made (one per load case per d tried).
        tried: (d, total steps or None when some load case did not settle) for every d tried.
        work: time steps simulated by the whole search, every run and load case together
            (its cost in kernel steps, the final runs included).
        predicted: the fastest d predicted from the modes before any run, N s/m (None: the
            search started from the critical-damping estimates).
        max_steps: the cap on each run's steps (the spec's, or 'auto' resolved).
        residuals: (L,) the largest unbalanced nodal force of each case's last sweep at d, N.
    """

    d: float
    steps: list[int]
    displacements: np.ndarray
    d_min: float
    guess: float
    runs: int
    tried: list[tuple[float, int | None]] = field(default_factory=list)
    work: int = 0
    predicted: float | None = None
    max_steps: int = 0
    residuals: list[float] = field(default_factory=list)

    @property
    def total_steps(self) -> int:
        return int(sum(self.steps))


def fastest_damping(
    problem: Problem,
    stiffness: Stiffness | np.ndarray,
    depth: int | None,
    bounds: tuple[float, float],
    guesses: tuple[float, float],
    *,
    dt: float | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    prediction: Prediction | None = None,
    models: list[StepModel] | None = None,
    max_steps: int | None = None,
    auto: bool = False,
    spread: Spread | None = None,
    settle: Sequence[float] | None = None,
    targets: np.ndarray | None = None,
    distances: Sequence[float] | None = None,
    why: Sequence[str] | None = None,
    settings: DampingSettings = DEFAULT,
) -> DampingFit:
    """The d in ``bounds`` (N s/m) that settles every load case in the fewest total steps, at
    ``stiffness`` (a :class:`~fpm.model.forces.Stiffness` or (S,) N/m), ``depth`` (None: every
    layer) and ``dt`` s (None: the spec's, 'auto' resolved at ``stiffness``).

    Starts at ``prediction`` (the fastest d the modes predict; ``models``, its reduced steps,
    also place the margin's first probe), else brackets from ``guesses`` (two estimates of d,
    clipped into the bounds). ``max_steps`` caps each run (None: the spec's); with ``auto``
    (fpm.max_steps 'auto') a search in which nothing settles is repeated under a grown cap.
    ``spread`` runs the runs over other processes (the answer does not depend on it).
    ``settle`` (L,) N/m, ``targets`` (L, N, 3) m and ``distances`` (L,): the runs' settle
    criterion (:func:`fpm.dynamics.settle.run_criterion`). ``why``: per load case what may
    keep it from settling, said when it cannot. ``progress`` is called with {"d",
    "total_steps"} after each d tried.

    Raises:
        DampingError: no d in the bounds settles every load case within max_steps, or a
            load case cannot settle within the step budget
            (:func:`fpm.fitting.damping.unsettled.hopeless`).
    """
    if max_steps is None:
        value = problem.spec.fpm.max_steps
        auto = auto or value == "auto"
        max_steps = FALLBACK_STEPS if value == "auto" else int(value)
    step = time_step(problem, stiffness) if dt is None else dt
    limit = AUTO_CEILING if auto else max_steps  # the most steps a run may ever be given
    earlier: list[tuple[int, float, bool]] | None = None  # the predicted d's cases at its cap
    for attempt in range(settings.retries + 1):
        last = not auto or attempt == settings.retries or max_steps >= limit
        runs = _Runs(problem, stiffness, depth, step, spread, settle=settle, targets=targets,
                      distances=distances, settings=settings)  # fmt: skip
        runs.max_steps = max_steps
        try:
            return _search(
                runs, bounds, guesses, progress, prediction, models, explain=last,
                grow=not last, limit=(limit, auto, list(why or [])), earlier=earlier,
            )  # fmt: skip
        except ShortCap as short:  # the predicted d's runs need more steps than the cap
            need, earlier = short.args
        except Hopeless:  # no larger cap helps
            raise
        except DampingError:
            if last:
                raise
            need, earlier = 0.0, None
        finally:
            runs.close()
        grown = max(settings.max_steps_growth * max_steps, 1.5 * need)
        max_steps = int(min(limit, grown))
    raise AssertionError("unreachable")


def _search(
    runs: _Runs,
    bounds: tuple[float, float],
    guesses: tuple[float, float],
    progress: Callable[[dict[str, Any]], None] | None,
    prediction: Prediction | None = None,
    models: list[StepModel] | None = None,
    *,
    explain: bool = True,
    grow: bool = False,
    limit: tuple[int, bool, list[str]] | None = None,
    earlier: list[tuple[int, float, bool]] | None = None,
) -> DampingFit:
    """The search (:func:`fastest_damping`) under one cap. ``explain``: a failure says what
    would work (:func:`fpm.fitting.damping.unsettled.what_would_work`); ``grow``: the cap may
    grow, so the predicted d's runs reaching it unsettled raise :class:`ShortCap` at once;
    ``limit``: (the step budget, whether it is 'auto''s, per case what may keep it from
    settling) against which a hopeless case ends the search, ``earlier`` its (steps,
    predicted steps, still moving) per case at the last cap
    (:func:`fpm.fitting.damping.unsettled.hopeless`)."""
    lo, hi = round(math.log(bounds[0]), 12), round(math.log(bounds[1]), 12)
    max_steps, settings = runs.max_steps, runs.settings
    steps: dict[float, list[int] | None] = {}  # log d -> steps per case (None: not settled)
    slower: dict[float, int] = {}  # log d -> steps taken when stopped (at least the best total)
    # log d -> predicted steps per case, for a d stopped on its prediction
    forecast: dict[float, tuple[float, ...]] = {}
    # [log d, displacements (L, N, 3), residuals (L,) N] of the fewest total steps so far
    best: list[Any] = []
    short: dict[float, float] = {}  # log d -> steps it needs, for a d stopped by the cap
    # log d -> (steps taken, steps predicted) per case, for a d stopped by the cap
    needs: dict[float, list[tuple[int, float, bool]]] = {}

    def capped(results: Sequence[DynamicRun | CaseRun]) -> bool:
        """A case stopped at the cap unsettled (its verdict may still read 'done' when the
        cap falls between two milestones)."""
        return any(not r.finished and r.steps >= max_steps for r in results)

    def key(y: float) -> float:
        """log d within the bounds, rounded: one key per d, whatever path computed it."""
        return round(min(max(y, lo), hi), 12)

    def total(
        y: float,
        prune: float = settings.prune,
        to_cap: bool = False,
        beside: Sequence[Request] = (),
    ) -> float:
        """Total steps at d = exp(y) (for a d stopped at the best total, the steps it had
        taken: a lower bound); inf if some case did not settle within max_steps.
        ``beside``: requests run at the same time as a d run ``to_cap``, under its total."""
        y = key(y)
        if y not in steps and y not in slower:
            # A d whose steps already add up to the best total cannot win: stop it there.
            budget = _total(steps[best[0]]) if best else None
            results: Sequence[DynamicRun | CaseRun]
            if budget is None and to_cap:  # each case's run is its own: they may run apart
                results, verdict = runs.separate(math.exp(y), [max_steps] * runs.cases, beside)
            else:
                results, verdict = runs(
                    math.exp(y), [max_steps] * runs.cases, budget, prune=prune, to_cap=to_cap
                )
            if verdict.outcome == "lost" and budget is not None:  # it cannot win
                slower[y] = int(min(max(budget, verdict.total), 1 << 62))
                if verdict.predicted:
                    forecast[y] = verdict.predicted
            elif budget is None and (verdict.outcome in ("lost", "failed") or capped(results)):
                steps[y] = None
                if not any(r.diverged for r in results):  # stopped by the cap
                    needs[y] = [
                        (
                            r.steps,
                            long_decay(r, settings) if not r.finished else float(r.steps),
                            not r.finished,
                        )
                        for r in results
                    ]
                    late = [n for _, n, _ in needs[y] if math.isfinite(n)]
                    extra = late if verdict.outcome == "done" else []  # no prediction made
                    short[y] = max([*verdict.predicted, *extra, 2.0 * max_steps])
            elif verdict.outcome == "done" and all(r.state == SETTLED for r in results):
                settled = [r.steps for r in results]
                steps[y] = settled
                if not best or sum(settled) < _total(steps[best[0]]):
                    best[:] = [
                        y,
                        np.stack([r.result().displacements for r in results]),
                        [r.history[-1][1] if r.history else 0.0 for r in results],
                    ]
            else:
                steps[y] = None
            if progress is not None:
                found = steps.get(y)
                progress({"d": math.exp(y), "total_steps": None if found is None else sum(found)})
        if y in slower:
            return float(slower[y])
        return float(_total(steps[y])) if steps[y] is not None else math.inf

    if prediction is not None:
        # Confirm: the predicted d, then a run on either side, each stopped as soon as it is
        # predicted no faster than its budget; walk on only where one of them is faster.
        y0 = min(max(math.log(prediction.d), lo), hi)
        step = math.log(settings.confirm)
        left, mid, right = max(y0 - step, lo), y0, min(y0 + step, hi)
        caps = (max_steps,) * runs.cases
        sides = [y for y in dict.fromkeys(key(y) for y in (left, right)) if y != key(mid)]
        # Where other workers are free the margin's edge probe runs beside the predicted d's,
        # its caps named from their steps should it stay the fastest
        # (:func:`fpm.fitting.damping.margin.smallest_settling`).
        beside: list[Request] = []
        edge = None
        if models is not None:
            edge = predicted_edge(models, math.exp(key(mid)), lo, max_steps, settings)
        if edge is not None and round(edge, 12) < key(mid):
            beside.append(Request(math.exp(round(edge, 12)), caps, None, estimate=True,
                                  caps_later=True))  # fmt: skip
        # The predicted d runs to the cap: early in a long run its decay is no guide (on a
        # slender bar it can over-predict the steps several times).
        f_mid = total(mid, to_cap=True, beside=beside)
        if limit is not None and key(mid) in needs:
            hopeless(runs.problem, math.exp(key(mid)), needs[key(mid)], *limit, earlier, settings)
        if grow and key(mid) in short:
            raise ShortCap(short[key(mid)], needs.get(key(mid)))
        # A side runs only where the reduced steps cannot rule it out (:func:`_unsure`); both
        # at once where other workers are free: right's budget is mid's total unless left
        # turns out faster (then right runs anew, with left's).
        if models is not None:
            measured = steps.get(key(mid))
            sides = [y for y in sides if _unsure(models, measured, y, key(mid), settings)]
        budget = _total(steps[best[0]]) if best else None
        runs.prefetch(
            [
                Request(math.exp(y), caps, budget, prune=settings.confirm_prune)
                for y in sides if y not in steps and y not in slower
            ]
        )  # fmt: skip

        def confirmed(y: float) -> float:
            """Total steps at a side (inf: ruled out by the reduced steps, not run)."""
            if key(y) in sides or key(y) == key(mid):
                return total(y, settings.confirm_prune)
            return math.inf

        f_left, f_right = confirmed(left), confirmed(right)
    else:
        # Bracket: start from the two guesses and their geometric mean.
        g_low, g_high = sorted(min(max(math.log(g), lo), hi) for g in guesses)
        y0 = (g_low + g_high) / 2
        step = max((g_high - g_low) / 2, math.log(settings.bracket_step))
        left, mid, right = max(y0 - step, lo), y0, min(y0 + step, hi)
        f_mid, f_left, f_right = total(mid), total(left), total(right)
    # Walk towards fewer steps, each step 1.6x longer than the last, until the fewest are
    # bracketed.
    walk = step
    while f_left < f_mid and left > lo:
        walk *= settings.walk_growth
        right, f_right, mid, f_mid = mid, f_mid, left, f_left
        left = max(mid - walk, lo)
        f_left = total(left)
    while f_right < f_mid and right < hi:
        walk *= settings.walk_growth
        left, f_left, mid, f_mid = mid, f_mid, right, f_right
        right = min(mid + walk, hi)
        f_right = total(right)
    if not best:  # nothing settled around the start: scan the whole range
        for y in np.linspace(lo, hi, 9):
            total(float(y))
        if not best:
            raise DampingError(
                f"no d in [{bounds[0]:.3g}, {bounds[1]:.3g}] N s/m settles every load case "
                f"within max_steps={max_steps} at dt = {runs.dt:.3g} s"
                + (": " + what_would_work(runs, math.exp(y0), max_steps) if explain else "")
            )
    # Refine: golden-section steps between the best d and its tried neighbours.
    for _ in range(settings.refine_steps):
        if _flat(steps, best[0], settings):
            break
        y = _next_point([*steps, *slower], best[0], settings)
        if y is None:
            break
        total(y)
    y_best, displacements, residuals = best
    edge = None
    if models is not None:
        edge = predicted_edge(models, math.exp(y_best), lo, max_steps, settings)
    y_min = smallest_settling(runs, steps, forecast, y_best, lo, max_steps,
                              math.log(settings.bracket_step), edge, settings)  # fmt: skip
    tried = [(math.exp(y), None if s is None else sum(s)) for y, s in steps.items()]
    tried += [(math.exp(y), None) for y in slower]
    return DampingFit(
        d=math.exp(y_best), steps=list(steps[y_best] or []), displacements=displacements,
        d_min=math.exp(y_min), guess=math.exp(y0), runs=runs.count, tried=sorted(tried),
        work=runs.work, predicted=None if prediction is None else prediction.d,
        max_steps=max_steps, residuals=[float(r) for r in residuals],
    )  # fmt: skip


def _unsure(
    models: list[StepModel],
    measured: list[int] | None,
    y: float,
    y_mid: float,
    settings: DampingSettings = DEFAULT,
) -> bool:
    """Whether the confirming run at log d ``y`` is needed beside the predicted d (log
    ``y_mid``), whose runs settled in ``measured`` steps per case (None: they did not): yes
    unless the reduced steps predict ``y`` slower than ``y_mid`` by more than ``settings.trust``
    times their own relative error at ``y_mid`` (an offset nearby d share)."""
    if not measured:
        return True
    predicted = total_steps(models, math.exp(y_mid), SCHEMA_MAX_STEPS)
    if not (math.isfinite(predicted) and predicted > 0):
        return True
    error = abs(sum(measured) - predicted) / sum(measured)
    excess = (total_steps(models, math.exp(y), SCHEMA_MAX_STEPS) - predicted) / predicted
    return not excess > settings.trust * error


def _total(steps: list[int] | None) -> int:
    return sum(steps) if steps is not None else 1 << 62


def _flat(steps: dict[float, list[int] | None], y_best: float, settings: DampingSettings) -> bool:
    """The best d's two tried neighbours both settled within ``settings.flat`` of its total
    steps: a d between them could gain at most that."""
    tried = sorted(steps)
    i = tried.index(y_best)
    neighbours = [steps[y] for y in tried[max(i - 1, 0) : i] + tried[i + 1 : i + 2]]
    best = _total(steps[y_best])
    return len(neighbours) == 2 and all(
        n is not None and _total(n) <= (1 + settings.flat) * best for n in neighbours
    )


def _next_point(tried: list[float], y_best: float, settings: DampingSettings) -> float | None:
    """Where to look next (log d): a golden-section step into the wider of the gaps between the
    best d and its tried neighbours (every other tried d is slower, stopped at the best total,
    or does not settle), or None once both gaps are below ``settings.resolution``."""
    tried = sorted(tried)
    i = tried.index(y_best)
    neighbours = tried[max(i - 1, 0) : i] + tried[i + 1 : i + 2]
    gaps = [n - y_best for n in neighbours]
    if not gaps:
        return None
    wide = max(gaps, key=abs)
    if abs(wide) < 2 * math.log(settings.resolution):
        return None
    return y_best + GOLDEN * wide
