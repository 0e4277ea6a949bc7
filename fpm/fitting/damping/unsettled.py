"""When the d search's runs cannot settle (:mod:`fpm.fitting.damping.search`): the errors it
raises, the step budget a load case is judged against, and what would work instead (the
settings named here are those of :class:`fpm.fitting.damping.settings.DampingSettings`).

A run at the predicted d that reaches its cap unsettled is read by the decay of its residual
over the whole run (:func:`long_decay`); a case whose decay predicts more than ``hopeless`` times
the step budget, or whose settling recedes as its cap grows, ends the search at once
(:func:`hopeless`, :class:`Hopeless`). Where no d settles at all, :func:`what_would_work` says
the dt and step cap that would.
"""

from __future__ import annotations

import math

from ...dynamics.simulation import DynamicRun
from ...dynamics.stability import auto_time_step
from ...dynamics.step_caps import SCHEMA_MAX_STEPS
from ...dynamics.voigt import SETTLED
from ...model.problem import Problem
from .lockstep import CaseRun, _Runs
from .settings import DEFAULT, DampingSettings


def _read_after(need: float, limit: int, settings: DampingSettings) -> float:
    """The steps a run at its cap must have taken before its decay (``need``, the steps it
    predicts; inf: not shrinking) may stop the search, against the budget ``limit``: at least
    ``settings.hopeless_after`` (or the budget, if smaller); a tenth of the budget for a run
    that has not shrunk at all."""
    return min(settings.hopeless_after, limit) if math.isfinite(need) else limit / 10


def hopeless(
    problem: Problem,
    d: float,
    needs: list[tuple[int, float, bool]],
    limit: int,
    auto: bool,
    why: list[str],
    earlier: list[tuple[int, float, bool]] | None = None,
    settings: DampingSettings = DEFAULT,
) -> None:
    """Raise :class:`DampingError` naming the load cases whose run at ``d`` (N s/m, the
    predicted d) stopped at its cap with a decay that predicts more than ``settings.hopeless`` times
    the step budget ``limit``: (steps taken, steps predicted, still moving) per case in ``needs``,
    ``why`` what may keep each from settling (none: nothing said). Also the cases that reached their
    cap unsettled again after it grew to what their decay predicted at the cap before (``earlier``,
    the same per case there): a run whose settling recedes as it goes (a creep, not the exponential
    decay the prediction assumes) cannot be given a cap that holds it."""
    slow = [
        j
        for j, (taken, need, moving) in enumerate(needs)
        if moving
        and taken >= _read_after(need, limit, settings)
        and not need <= settings.hopeless * limit
    ]
    receding = []
    if earlier is not None:
        receding = [
            j for j, ((taken, _, moving), (before, asked, _)) in
            enumerate(zip(needs, earlier, strict=True))
            if moving and taken > before and taken >= asked and j not in slow
        ]  # fmt: skip
    if not slow and not receding:
        return
    budget = (
        f"fpm.max_steps 'auto' grows to at most {limit:,}"
        if auto
        else (f"fpm.max_steps = {limit:,}")
    )
    parts = []
    for j in sorted(slow, key=lambda j: -needs[j][1]):
        taken, need, _ = needs[j]
        guess = (
            "has not shrunk over the second half of the run"
            if not math.isfinite(need)
            else f"predicts about {need:.2g} steps"
        )
        cause = f" ({why[j]})" if j < len(why) and why[j] else ""
        parts.append(
            f"load case '{problem.load_cases[j].name}' cannot settle within the step budget "
            f"({budget}): at d = {d:.3g} N s/m, the fastest the lattice's slowest modes "
            f"predict, its run is still moving after {taken:,} steps and its distance from "
            f"equilibrium {guess}{cause}"
        )
    for j in receding:
        taken, need, _ = needs[j]
        before, asked, _ = earlier[j] if earlier is not None else (0, 0.0, False)
        cause = f" ({why[j]})" if j < len(why) and why[j] else ""
        after = "no longer shrinks" if not math.isfinite(need) else f"predicts {need:.2g} steps"
        parts.append(
            f"load case '{problem.load_cases[j].name}' does not settle: at d = {d:.3g} N s/m, "
            f"the fastest the lattice's slowest modes predict, its run was still moving after "
            f"{before:,} steps, where its decay predicted {asked:.2g}; given {taken:,} it is "
            f"still moving and its distance from equilibrium {after}: it creeps rather than "
            f"settles{cause}"
        )
    slow += receding
    most = max(needs[j][1] for j in slow)
    if not auto and most <= SCHEMA_MAX_STEPS:  # the spec's own cap is what is short
        advice = f"raise fpm.max_steps to about {math.ceil(1.2 * most):,}, or set it 'auto'"
    else:
        advice = (
            "lower its forces (a press of a few % of the solid's smallest extent settles in "
            "thousands of steps), or check that the fixed nodes hold the solid"
        )
    raise Hopeless("; ".join(parts) + ": " + advice)


def long_decay(run: DynamicRun | CaseRun, settings: DampingSettings = DEFAULT) -> float:
    """The steps ``run`` (stopped at its cap) would take to settle, predicted from the decay of
    its residual over the whole run: the envelope (largest sample) over its last quarter
    against that over the quarter before, extrapolated exponentially down to its settle
    force (as :func:`fpm.fitting.damping.lockstep.predicted_steps` does over the last two pieces of
    ``settings.chunk`` steps, which a slow mode's swing, thousands of steps long, can fill with
    a rising envelope); inf when the envelope has not fallen; its steps when it never settles
    (settle force 0) or is too short to read (under 2 chunks a quarter, the first swing)."""
    at = run.steps
    span = at // 4
    last = [r for n, r in run.history if at - span < n <= at]
    before = [r for n, r in run.history if at - 2 * span < n <= at - span]
    if run.settle_force <= 0 or span < 2 * settings.chunk or not last or not before:
        return float(at)
    e1, e2 = max(before), max(last)
    if not (0 < e2 < e1):
        return math.inf
    return at + max(math.log(e2 / run.settle_force), 0.0) / (math.log(e1 / e2) / span)


def what_would_work(runs: _Runs, d: float, max_steps: int) -> str:
    """Numbers for a run that cannot settle: the dt 'auto' would take (half the stability
    estimate, at most 1 ms) and the steps a run at d needs there, measured by one probe of up to
    ``probe_steps`` x max_steps steps per load case (``runs.settings``) (capped at 10^6; none where
    that is the search's own dt and cap, whose runs already said it)."""
    p = runs.problem
    dt = min(runs.dt, auto_time_step(p, runs.stiffness))
    cap = min(1_000_000, runs.settings.probe_steps * max_steps)
    if dt >= runs.dt and cap <= max_steps:  # the search's own runs were that probe
        return (
            f"even at fpm.dt = {dt:.3g} s (half the lattice's stability estimate) no d settles "
            f"within {max_steps} steps: lower the loads, or check that the fixed nodes hold the "
            "solid; widening annealing.bounds.d may help"
        )
    probe = _Runs(p, runs.stiffness, runs.depth, dt, settings=runs.settings)
    try:
        results, _ = probe(d, [cap] * probe.cases)
    finally:
        probe.close()
    steps = [r.steps for r in results]
    if all(r.state == SETTLED for r in results):
        need = max(steps)
        return (
            f"at fpm.dt = {dt:.3g} s (half the lattice's stability estimate, at most 1 ms) and "
            f"d = {d:.3g} N s/m every load case settles within {need} steps: set fpm.dt <= "
            f"{dt:.3g} and fpm.max_steps >= {int(math.ceil(1.2 * need))}"
        )
    return (
        f"even at fpm.dt = {dt:.3g} s (half the lattice's stability estimate) and d = "
        f"{d:.3g} N s/m a run does not settle within {cap} steps: lower the loads, or check "
        "that the fixed nodes hold the solid; widening annealing.bounds.d may help"
    )


class DampingError(RuntimeError):
    """No d in the bounds settles every load case. ``predicted``: the fastest d the modes
    predicted, N s/m, where the search knew it (None: not)."""

    predicted: float | None = None


class Hopeless(DampingError):
    """A load case cannot settle within the step budget, whatever its cap (:func:`hopeless`):
    the search ends at once, with no retry under a larger cap."""


class ShortCap(Exception):
    """The predicted d's runs reached the cap unsettled; ``args[0]``: the steps they need."""
