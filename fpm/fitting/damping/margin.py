"""The d search's stability margin: the smallest d that still settles every load case within
``margin_cap`` times its steps at the fastest d (below it runs diverge or creep)."""

from __future__ import annotations

import math

from ...dynamics.reduced_step import StepModel
from ...dynamics.voigt import SETTLED
from .lockstep import Request, _Runs
from .settings import DEFAULT, DampingSettings


def predicted_edge(
    models: list[StepModel],
    d_best: float,
    lo: float,
    cap: int,
    settings: DampingSettings = DEFAULT,
) -> float | None:
    """log d of the reduced steps' estimate of the margin: the smallest d (bisection on log d,
    to 1%) whose predicted steps stay within ``margin_cap`` times theirs at ``d_best`` in
    every load case; None where they do not settle at ``d_best``."""
    fastest = [m.steps(d_best, cap) for m in models]
    if not all(math.isfinite(f) and f > 0 for f in fastest):
        return None
    caps = [settings.margin_cap * f for f in fastest]

    def within(y: float) -> bool:
        return all(m.steps(math.exp(y), int(c) + 1) <= c for m, c in zip(models, caps, strict=True))

    ok, fail = math.log(d_best), lo
    if within(fail):
        return fail
    while ok - fail > math.log(1.01):
        middle = (ok + fail) / 2
        if within(middle):
            ok = middle
        else:
            fail = middle
    return ok


def smallest_settling(
    runs: _Runs,
    steps: dict[float, list[int] | None],
    forecast: dict[float, tuple[float, ...]],
    y_best: float,
    lo: float,
    max_steps: int,
    step: float,
    edge: float | None = None,
    settings: DampingSettings = DEFAULT,
) -> float:
    """log d of the smallest d whose runs all settle within ``margin_cap`` times their steps at
    the fastest d. The d the search tried answer first (their steps, or the predictions they
    were stopped on: ``forecast``); then ``edge`` (log d, the reduced steps' estimate), and
    ``step / 2`` below it where it settles, ``margin_probes`` probes at most; without an edge
    the walk goes down by ``step`` and bisects to ``step / 2``. A probe stops once its decay
    predicts the answer, so d_min is an estimate where runs are long."""
    fastest = steps[y_best] or []
    caps = [min(max_steps, settings.margin_cap * s) for s in fastest]

    def known(y: float) -> bool | None:
        """Whether the search's own runs at y settle within the caps (None: not known)."""
        if steps.get(y) is not None:
            return all(s <= c for s, c in zip(steps[y] or [], caps, strict=True))
        if y in forecast:
            return all(p <= c for p, c in zip(forecast[y], caps, strict=True))
        return None

    answers = {y: known(y) for y in [*steps, *forecast] if y <= y_best}

    probes = [0]

    def settles(y: float) -> bool:
        answer = answers.get(y)
        if answer is None:
            probes[0] += 1
            results, verdict = runs(math.exp(y), caps, estimate=True)
            answer = verdict.outcome == "settles" or (
                verdict.outcome == "done"
                and all(
                    r.state == SETTLED and r.steps <= c for r, c in zip(results, caps, strict=True)
                )
            )
            answers[y] = answer
        return answer

    y_ok = min(y for y, ok in answers.items() if ok)
    failing = [y for y, ok in answers.items() if ok is False and y < y_ok]
    y_fail = max(failing) if failing else None

    def open_(y: float) -> bool:
        """y lies inside the bracket (y_fail, y_ok)."""
        return y < y_ok and (y_fail is None or y > y_fail)

    if edge is not None and open_(round(edge, 12)):
        edge = round(edge, 12)
        if answers.get(edge) is None:  # at once where another worker is free
            runs.prefetch([Request(math.exp(edge), tuple(caps), None, estimate=True)])
        if settles(edge):  # then half a walk's step below it
            y_ok = edge
            below = round(max(edge - step / 2, lo), 12)
            if open_(below):
                if settles(below):
                    y_ok = below
                else:
                    y_fail = below
        else:
            y_fail = edge
    limit = settings.margin_probes if edge is not None else math.inf
    if y_fail is None:
        while y_ok > lo and probes[0] < limit:
            y = round(max(y_ok - step, lo), 12)
            if not settles(y):
                y_fail = y
                break
            y_ok = y
    while y_fail is not None and y_ok - y_fail > step / 2 + 1e-12 and probes[0] < limit:
        middle = (y_fail + y_ok) / 2
        if settles(middle):
            y_ok = middle
        else:
            y_fail = middle
    return y_ok
