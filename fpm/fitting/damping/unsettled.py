"""When the d search's runs cannot settle: its errors, the step budget a load case is judged
against (:func:`hopeless`), and what would work instead (:func:`what_would_work`)."""

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
    """The steps a run at its cap must have taken before its decay (``need``; inf: not
    shrinking) may stop the search against the budget ``limit``."""
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
    """Raise :class:`Hopeless` naming the load cases whose run at the predicted ``d`` (N s/m)
    stopped at its cap with a decay predicting more than ``settings.hopeless`` times the step
    budget ``limit`` ((steps taken, steps predicted, still moving) per case in ``needs``;
    ``why``: what may keep each from settling), or that reached their cap unsettled again
    after it grew to what their decay predicted at the cap before (``earlier``): a creep."""
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
    """The steps ``run`` (stopped at its cap) would take to settle, from the decay of its
    residual over the whole run: the envelope over its last quarter against the quarter
    before, extrapolated to its settle force (a slow mode's swing can fill two chunks with a
    rising envelope); inf where it has not fallen; its steps where it never settles or is too
    short to read (under 2 chunks a quarter)."""
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
    """Numbers for a run that cannot settle: the dt 'auto' would take and the steps a run at d
    needs there, by one probe of up to ``probe_steps`` x max_steps steps per load case (none
    where that is the search's own dt and cap)."""
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
