"""Stage 2 of the calibration: the nodal damping d that settles fastest (docs/physics.md).

A settled FPM state does not depend on d; d only decides how fast, and whether, a run settles
at the spec's dt. So once the stiffness is fitted, d is chosen for the real-time loop: the value
in the search bounds that settles every load case in the fewest total time steps, found with the
real dynamic kernel (:class:`fpm.dynamics.simulation.FpmModel`).

Where the search starts. Normally from the prediction of :mod:`fpm.dynamics.modes`: the
lattice's slowest modes at the fitted stiffness, the FPM step reduced to them, and the d with
the fewest predicted steps (on the paper's cube and the soft organ within 1-3% of the runs'
fastest). The search (:func:`fastest_damping`) then confirms it with a run on either side,
CONFIRM apart, each stopped as soon as its decay predicts it slower than the prediction's own
runs (a few hundred steps), walks on only if one of them is faster (each step 1.6x longer,
until the fewest total steps are bracketed) and refines by a few golden-section steps between
the best d and its neighbours where they are still far apart. The margin (the smallest d that
still settles every load case within MARGIN_CAP times its fastest steps: the stability margin,
the fastest d sits near that edge and below it runs diverge or creep) starts from the reduced
step's own estimate of that edge: a probe 12% below it and one a walk's step further (the edge
itself only if the first does not settle).

Without a prediction (a lattice at rest that is a mechanism, e.g. 'axis' springs), from two
critical-damping estimates (:func:`critical_damping`): critical damping of a mode with nodal
damping d I and lumped masses M is d = 2 omega (u^T M u) / (u^T u), and Rayleigh's quotient of
a shape u that loads f hold, omega^2 = f.u / (u^T M u), estimates omega. Two shapes bracket the
slow motion a load excites: the static deflection u0 = K^-1 f and the deflection under its own
inertia, u1 = K^-1 M u0 (one step of inverse iteration). The search starts from the two and
their geometric mean and walks and refines as above; the margin comes from the d already tried
(their steps, or the predictions they were dropped on) and then by walking down and bisecting.

Runs advance in pieces of CHUNK steps (:class:`fpm.dynamics.simulation.DynamicRun`), all load cases
together, and a d is dropped as soon as its load cases have taken as many steps between them as
the best d's total: it can no longer win, so a poor d costs at most the best total, not a
full run of every case. Earlier still, once every running case has taken PREDICT_AFTER steps, the
decay of its residual (the largest unbalanced force, sampled every SAMPLE steps; its envelope
over the last two pieces) predicts the steps it still needs, and a d whose predicted total
exceeds PRUNE times the best total is dropped then; likewise a margin probe whose predicted
steps exceed PRUNE times its cap. A prediction only ever drops a d: every figure the search
returns comes from runs that settled. The runs of the fastest d are kept: they are the
calibration's final dynamic check.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from ..dynamics.modes import (
    FALLBACK_STEPS,
    SCHEMA_MAX_STEPS,
    Prediction,
    StepModel,
    fixed_max_steps,
)
from ..dynamics.settle import force_tolerance
from ..dynamics.simulation import DynamicRun, FpmModel
from ..dynamics.stability import auto_time_step, time_step
from ..dynamics.voigt import DIVERGED, INVERTED, RUNNING, SETTLED
from ..model.forces import Stiffness
from ..model.problem import Problem

BRACKET_STEP = 1.25
"""Smallest first step of the bracket, as a factor on d (used when the two guesses are closer
than this)."""
WALK_GROWTH = 1.6
"""Each further bracket step is this much longer (on log d) than the last."""
RESOLUTION = 1.02
"""The refinement stops once the best d's neighbours are within this factor squared of it."""
GOLDEN = (3 - math.sqrt(5)) / 2
"""Golden-section fraction: where in the wider gap the next d goes."""
REFINE_STEPS = 4
"""At most this many refining runs after the bracket."""
FLAT = 0.02
"""The refinement stops once both neighbours of the best d settle within this fraction of its
total steps (the steps-versus-d curve is flat there)."""
CHUNK = 200
"""Time steps each load case advances between checks of a d's running total."""
MARGIN_CAP = 2
"""A d 'still settles' for the margin if every load case settles within this many times its
steps at the fastest d (below the margin a run diverges or creeps; capping keeps the margin
search as cheap as the rest)."""
SAMPLE = 25
"""Steps between the residual samples a run's decay is read from."""
PREDICT_AFTER = 3 * CHUNK
"""A run's remaining steps are predicted only once it has taken this many (past the transient)."""
PRUNE = 1.1
"""A d is dropped once its predicted total exceeds this times the best total (a margin probe:
once a case's predicted steps exceed this times its cap); the slack absorbs prediction error."""
MARGIN_PROBES = 2
"""With a prediction, the margin search asks for at most this many probes: 12% below the
reduced step's edge and a walk's step (1.25x) below that, or the edge itself where the first
does not settle (:func:`_first_probes`; where workers are free the walk's step runs at once
with the first, wasted if that does not settle). d_min is then the smallest d found that
settles, bracketed to 1.12x or 1.25x. On the 93,705-node organ the open walk down had taken
5 probes of up to 2 x 2,400 steps per load case, more than the fastest d's own runs; the edge,
12% below it and a step further took 3, and gave the same d_min and bracket as these 2."""
CONFIRM = 1.04
"""The runs that confirm a predicted d sit this factor below and above it."""
CONFIRM_PRUNE = 1.0
"""A confirming run is dropped once its predicted total exceeds the predicted d's total (it
would at best tie; the predicted d is kept)."""
LATER = -1
"""A :class:`Request`'s budget that is named once the runs have started: the confirming d's,
run beside the predicted d's whose total is their budget (:meth:`_Runs.separate`)."""
LOOK = 0.2
"""Seconds between a lockstep's looks for what is named later."""
HOLD = PREDICT_AFTER + 2 * CHUNK
"""Until what it needs is named, a lockstep's cases run at most this many steps and then wait:
past PREDICT_AFTER, where the verdicts of the d run beside the predicted d's usually come
(their cores go to the predicted d's cases meanwhile)."""
RETRIES = 2
"""With fpm.max_steps 'auto', a search in which nothing settles within the predicted cap is
repeated this many times more with MAX_STEPS_GROWTH times the cap (up to the schema's 10^6)."""
MAX_STEPS_GROWTH = 4


@dataclass
class DampingFit:
    """The fastest-settling d for a fitted stiffness.

    Attributes:
        d: nodal damping, N s/m.
        steps: (L,) time steps each load case takes to settle at d.
        displacements: (L, N, 3) the settled displacements at d, m.
        d_min: smallest d found that settles every load case within MARGIN_CAP times its
            steps at d, N s/m (to a factor of about 1.12; the lower bound if that settles).
        guess: where the search started, N s/m: the predicted d, or the geometric mean of the
            two critical-damping estimates.
        runs: dynamic runs made (one per load case per d tried).
        tried: (d, total steps or None when some load case did not settle) for every d tried.
        work: time steps simulated by the whole search, every run and load case together
            (its cost in kernel steps, the final runs included).
        predicted: the fastest d predicted from the modes before any run, N s/m (None: the
            search started from the critical-damping estimates).
        predicted_steps: (L,) the steps predicted per load case at ``predicted``.
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
    predicted_steps: list[float] = field(default_factory=list)
    max_steps: int = 0
    residuals: list[float] = field(default_factory=list)

    @property
    def total_steps(self) -> int:
        return int(sum(self.steps))


def critical_damping(
    problem: Problem, displacements: np.ndarray, loads: np.ndarray | None = None
) -> float:
    """Critical damping estimate, N s/m, from shapes (L, N, 3) held by ``loads`` (L, N, 3), N
    (None: each load case's forces, so the shapes are static displacements).

    The geometric mean over load cases of ``2 omega (u^T M u) / (u^T u)`` with Rayleigh's
    ``omega^2 = f.u / (u^T M u)``.
    """
    m = problem.solid.masses
    estimates = []
    for j, case in enumerate(problem.load_cases):
        u = displacements[j]
        f = case.dense(problem.n_nodes) if loads is None else loads[j]
        mu2 = float(np.einsum("n,ni,ni->", m, u, u))
        u2 = float(np.einsum("ni,ni->", u, u))
        work = float(np.einsum("ni,ni->", f, u))
        if mu2 > 0 and work > 0:
            estimates.append(2 * math.sqrt(work / mu2) * mu2 / u2)
    if not estimates:
        raise ValueError("no load case moves: cannot estimate the damping")
    return float(np.exp(np.mean(np.log(estimates))))


def _piece(run: DynamicRun, steps: int) -> int:
    """Advance ``run`` by ``steps``, in samples of SAMPLE steps (its residual history); returns
    the steps taken."""
    start = run.steps
    while run.steps - start < steps and not run.advance(min(SAMPLE, steps - run.steps + start)):
        pass
    return run.steps - start


def _timed_piece(run: DynamicRun, steps: int) -> tuple[int, float]:
    """:func:`_piece` on a pool thread: (the steps taken, the CPU seconds that thread spent)."""
    cpu = time.thread_time()
    return _piece(run, steps), time.thread_time() - cpu


_LOCKSTEP_CPU = threading.local()


def lockstep_cpu() -> float:
    """The CPU seconds that the lockstep runs started from this thread (:meth:`_Runs.locked`)
    have spent on the pool's threads so far: added to the thread's own ``time.thread_time()``
    it is what a request run here cost, wherever its pieces ran."""
    return float(getattr(_LOCKSTEP_CPU, "seconds", 0.0))


def _spent(future: Future[tuple[int, float]]) -> int:
    """A piece's steps; its CPU seconds counted for the thread that started the lockstep."""
    steps, cpu = future.result()
    _LOCKSTEP_CPU.seconds = lockstep_cpu() + cpu
    return steps


@dataclass
class CaseRun:
    """One load case run on its own to its end (settled, diverged, or ``cap`` steps), as the
    search reads it: what :func:`verdict_at` and :func:`predicted_steps` read of a
    :class:`~fpm.dynamics.simulation.DynamicRun`, and the settled displacements. JSON-able but
    for ``displacements``, which travels as raw float64 bytes (:mod:`fpm.fitting.case_runs`).

    Attributes:
        steps: time steps taken; state: voigt.RUNNING (reached its cap), SETTLED or DIVERGED
            (or INVERTED); settle_force: the residual it settles below, N.
        history: (steps, residual N) after every SAMPLE steps.
        displacements: (N, 3) where it settled, m ((0, 3) unless settled).
    """

    steps: int
    state: int
    settle_force: float
    history: list[tuple[int, float]]
    displacements: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def diverged(self) -> bool:
        return self.state in (DIVERGED, INVERTED)

    @property
    def finished(self) -> bool:
        return self.state != RUNNING

    def result(self) -> CaseRun:
        """Itself (the search reads ``result().displacements`` of a run)."""
        return self

    @classmethod
    def of(cls, run: DynamicRun | CaseRun) -> CaseRun:
        """Where ``run`` stands (its displacements only if it settled)."""
        if isinstance(run, CaseRun):
            return run
        settled = run.state == SETTLED
        return cls(
            steps=run.steps,
            state=run.state,
            settle_force=run.settle_force,
            history=list(run.history),
            displacements=run.result().displacements if settled else np.zeros((0, 3)),
        )


@dataclass(frozen=True)
class Request:
    """One d's lockstep runs as the search asks for them (:meth:`_Runs.__call__`'s
    arguments): d (N s/m), each case's cap, the budget (None: none; LATER: named once the
    runs have started), and how predictions decide; ``caps_later``: the caps are named once
    the runs have started, within ``caps`` (a margin probe's, run beside the predicted d's
    whose steps set them)."""

    d: float
    caps: tuple[int, ...]
    budget: int | None
    estimate: bool = False
    prune: float = PRUNE
    to_cap: bool = False
    caps_later: bool = False


Outcome = tuple[list["CaseRun"], "Verdict"]
"""A d's runs (where each case stood when the d was decided) and its verdict."""


def run_case(
    model: FpmModel,
    stiffness: Stiffness | np.ndarray,
    depth: int | None,
    dt: float,
    load_case: int,
    d: float,
    cap: int,
    settle_stiffness: float | None = None,
) -> CaseRun:
    """Load case ``load_case`` at (``stiffness``, ``d`` N s/m, ``depth``, ``dt`` s) from rest
    to its end: settled, diverged or ``cap`` steps; advanced in the same pieces of CHUNK steps
    as the lockstep runs of :class:`_Runs`, so the very same floating-point sequence whatever
    process runs it. ``settle_stiffness``: the distance criterion's, N/m
    (:mod:`fpm.dynamics.settle`); None: the force criterion."""
    run = model.start(
        load_case, k=stiffness, d=d, depth=depth, dt=dt,
        **settle_criterion(model.problem, settle_stiffness),
    )  # fmt: skip
    while not run.finished and run.steps < cap:
        _piece(run, min(CHUNK, cap - run.steps))
    return CaseRun.of(run)


def settle_criterion(problem: Problem, settle_stiffness: float | None) -> dict[str, float]:
    """A run's settle arguments (:meth:`FpmModel.start`): the distance criterion's
    ``settle_stiffness`` (N/m) alone, or, for None, the force criterion's tolerance."""
    if settle_stiffness is None:
        return {"settle_tolerance": force_tolerance(problem.spec), "settle_stiffness": 0.0}
    return {"settle_tolerance": 0.0, "settle_stiffness": float(settle_stiffness)}


Resolve = Callable[[], dict[str, Any] | None]
"""Where a lockstep learns what is named later (None: not yet): {"budget": int or None} for
a budget LATER, {"caps": [int per case], or None: drop the request} for caps named later
(:func:`named_later`)."""


def run_request(
    problem: Problem,
    stiffness: Stiffness | np.ndarray,
    depth: int | None,
    dt: float,
    request: Request,
    resolve: Resolve | None = None,
    settle: Sequence[float] | None = None,
) -> Outcome:
    """One d's lockstep runs (:meth:`_Runs.locked`) at (``stiffness``, ``depth``, ``dt`` s)
    in this process, for another's search; ``resolve``: where what is named later (a budget
    LATER, or caps) comes from; ``settle``: each case's settle stiffness (as :class:`_Runs`)."""
    runs = _Runs(problem, stiffness, depth, dt, settle=settle)
    try:
        return runs.locked(request, resolve)
    finally:
        runs.close()


def settled_total(runs: list[CaseRun], caps: list[int]) -> int | None:
    """The total steps of a d whose cases each ran on their own to their end, as the search
    takes it for the best so far (:func:`replay_verdict` done and every case settled), else
    None."""
    if replay_verdict(runs, caps).outcome == "done" and all(r.state == SETTLED for r in runs):
        return sum(r.steps for r in runs)
    return None


def named_later(request: Request, runs: list[CaseRun], caps: list[int]) -> dict[str, Any]:
    """What ``request``, run beside a d's cases (``runs``, each to ``caps``), learns once
    they have ended, as the search would make it with that d the best so far: a confirming
    d's budget, their :func:`settled_total`; a margin probe's caps, MARGIN_CAP times each
    case's steps within the request's own (None when they did not all settle: then the
    search makes no such probe)."""
    total = settled_total(runs, caps)
    if not request.caps_later:
        return {"budget": total}
    if total is None:
        return {"caps": None}
    return {"caps": [min(c, MARGIN_CAP * r.steps) for r, c in zip(runs, request.caps, strict=True)]}


def _capped(run: DynamicRun, cap: int) -> DynamicRun | CaseRun:
    """``run`` as it would stand had it been capped at ``cap`` steps (a run that went on
    past a cap named later): its state and residual history up to there (the kernel checks
    settling every step, so a run that ended by the cap ended the same way)."""
    if run.steps <= cap:
        return run
    return CaseRun(
        steps=cap,
        state=RUNNING,
        settle_force=run.settle_force,
        history=[(n, r) for n, r in run.history if n <= cap],
    )


class Spread(Protocol):
    """How the search's runs may be spread over other processes (the worker's:
    :class:`worker.spread.CaseSpread`). Whatever runs them, the runs are the same, so the
    search's answer does not depend on it."""

    def separate(
        self,
        d: float,
        caps: list[int],
        local: Callable[[int, float, int], CaseRun],
        beside: list[Request],
        local_request: Callable[[Request, Resolve], Outcome],
    ) -> tuple[list[CaseRun], list[Outcome | None]]:
        """Every load case of one d run on its own to its end, ``[CaseRun per case]``, where
        ``local(j, d, cap)`` runs case j in this process (:func:`run_case`); and, only when
        other workers are free, the requests ``beside`` at the same time, learning what
        :func:`named_later` makes of the cases' runs (a budget LATER, or caps) once those
        have all ended: their outcomes in order (None: not run), ``local_request(request,
        resolve)`` running one here."""
        ...

    def ahead(
        self, requests: list[Request], local: Callable[[Request], Outcome]
    ) -> list[Outcome | None]:
        """Requests the search will probably make next, at once (:meth:`_Runs.prefetch`):
        their outcomes in order (None: not run), ``local`` running one here."""
        ...


def replay_verdict(runs: list[CaseRun], caps: list[int]) -> Verdict:
    """The verdict the lockstep runs of :class:`_Runs` reach for a d run to its cap with no
    budget (the predicted d's runs), from its cases run each to its end: the milestones every
    CHUNK steps in turn, as the lockstep checks them, until one decides ``failed`` (a case
    diverged or reached its cap unsettled by it) or every case ended before it (``done``)."""
    verdict, milestone = Verdict("running"), CHUNK
    while verdict.outcome == "running" and not all(r.steps < milestone for r in runs):
        verdict = verdict_at(runs, caps, milestone, None, estimate=False, to_cap=True)
        milestone += CHUNK
    return Verdict("done") if verdict.outcome == "running" else verdict


class _Runs:
    """Runs every load case at one d, in pieces, on threads (the kernel releases the GIL).

    ``spread``: runs the predicted d's cases (no budget, to the cap: each case's run
    independent of the others') and the d the search will probably try next
    (:meth:`prefetch`) over other processes (:class:`Spread`; None: the cases on these
    threads, nothing ahead). ``settle``: each load case's settle stiffness, N/m (the distance
    criterion, :mod:`fpm.dynamics.settle`); None: the force criterion."""

    def __init__(
        self,
        problem: Problem,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        dt: float,
        spread: Spread | None = None,
        *,
        settle: Sequence[float] | None = None,
    ):
        self.problem = problem
        self.settle = None if settle is None else [float(s) for s in settle]
        self.stiffness = stiffness
        self.depth = depth
        self.dt = dt
        self.model = FpmModel(problem)
        self.cases = len(problem.load_cases)
        self.threads = min(self.cases, os.cpu_count() or 1)
        self.pool = ThreadPoolExecutor(self.threads)
        self.count = 0
        self.work = 0
        self.max_steps = fixed_max_steps(problem.spec.fpm.max_steps)  # each run's cap on steps
        self.spread = spread
        self.fetched: dict[Request, Outcome] = {}

    def local(self, load_case: int, d: float, cap: int) -> CaseRun:
        """Load case ``load_case`` at d run on its own to its end in this process."""
        return run_case(
            self.model, self.stiffness, self.depth, self.dt, load_case, d, cap,
            self.case_settle(load_case),
        )  # fmt: skip

    def case_settle(self, load_case: int) -> float | None:
        """Load case ``load_case``'s settle stiffness, N/m (None: the force criterion)."""
        return None if self.settle is None else self.settle[load_case]

    def separate(
        self, d: float, caps: list[int], beside: Sequence[Request] = ()
    ) -> tuple[list[CaseRun], Verdict]:
        """Every load case at d, each run on its own to its end (by ``spread``), and the
        verdict the lockstep would reach (:func:`replay_verdict`). For a d with no budget run
        to the cap, the same runs and verdict as :meth:`__call__`, but that a failed d's
        other cases also run to their end. ``beside``: requests the search will probably make
        next (a budget LATER, or caps named later: :func:`named_later` of this d's runs), run
        at the same time by ``spread`` where other workers are free, to be taken as
        :meth:`prefetch` ed."""
        if self.spread is None:
            runs = list(self.pool.map(self.local, range(self.cases), [d] * self.cases, caps))
        else:
            runs, outcomes = self.spread.separate(d, caps, self.local, list(beside), self.locked)
            for request, outcome in zip(beside, outcomes, strict=True):
                named = named_later(request, runs, caps)
                if "budget" in named:
                    self._keep([replace(request, budget=named["budget"])], [outcome])
                elif named["caps"] is not None:
                    taken = replace(request, caps=tuple(named["caps"]), caps_later=False)
                    self._keep([taken], [outcome])
        self.count += self.cases
        self.work += sum(r.steps for r in runs)
        return runs, replay_verdict(runs, caps)

    def prefetch(self, requests: list[Request]) -> None:
        """Run ``requests`` at once by ``spread`` (none without it), to be taken by the calls
        that make the very same requests (one that differs, e.g. in its budget, runs anew)."""
        requests = [r for r in requests if r not in self.fetched]
        if self.spread is None or not requests:
            return
        self._keep(requests, self.spread.ahead(requests, self.locked))

    def _keep(self, requests: list[Request], outcomes: list[Outcome | None]) -> None:
        """The outcomes of requests run ahead, for the calls that make them."""
        for request, outcome in zip(requests, outcomes, strict=True):
            if outcome is not None:
                self.fetched[request] = outcome

    def locked(self, request: Request, resolve: Resolve | None = None) -> Outcome:
        """``request``'s lockstep runs here, as :class:`CaseRun`; not counted in ``count``
        and ``work`` until the search takes them (:meth:`__call__`), whoever ran them.
        ``resolve``: where what is named later (a budget LATER, or caps) comes from. The CPU
        seconds its pieces spend on the pool's threads are credited to the calling thread
        (:func:`lockstep_cpu`)."""
        runs, verdict, _ = self._lockstep(request, resolve)
        return [CaseRun.of(run) for run in runs], verdict

    def __call__(
        self,
        d: float,
        caps: list[int],
        budget: int | None = None,
        *,
        estimate: bool = False,
        prune: float = PRUNE,
        to_cap: bool = False,
    ) -> tuple[Sequence[DynamicRun | CaseRun], Verdict]:
        """Every load case at d, case j for at most ``caps[j]`` steps, until every case has
        settled, one has diverged or reached its cap unsettled, or a :class:`Verdict` of
        :func:`verdict_at` ends it: at each milestone (every CHUNK steps) that every case has
        passed, the d is ``lost`` once the steps taken up to there add up to ``budget`` (None:
        no such limit), or once the predictions there exceed ``prune`` times the budget (PRUNE
        times a cap; with ``to_cap`` a case runs on to its cap whatever its decay predicts);
        with ``estimate`` it ``settles`` once every case is predicted within its cap.

        Decisions are taken only from each case's own state at the milestone, so they do not
        depend on how the threads happened to interleave: a search repeats exactly. A request
        run ahead (:meth:`prefetch`) is taken from there."""
        request = Request(d, tuple(caps), budget, estimate, prune, to_cap)
        if request in self.fetched:
            fetched, verdict = self.fetched.pop(request)
            self.count += self.cases
            self.work += sum(r.steps for r in fetched)
            return fetched, verdict
        runs, verdict, work = self._lockstep(request)
        self.count += self.cases
        self.work += work
        return runs, verdict

    def _lockstep(
        self, request: Request, resolve: Resolve | None = None
    ) -> tuple[list[DynamicRun | CaseRun], Verdict, int]:
        """:meth:`__call__`'s runs of ``request``, and the steps they took. A budget LATER
        or caps named later (by ``resolve``, looked at every LOOK seconds): until then the
        cases run on undecided, up to HOLD steps, then the milestones they have passed are
        decided in turn as they would have been with the budget or caps known (a case past
        its cap as it stood there), so the verdict is the same."""
        d, caps, budget = request.d, list(request.caps), request.budget
        pending = budget == LATER or request.caps_later
        if pending and resolve is None:
            raise ValueError("what is named later needs where to learn it")
        looked = -math.inf
        estimate, prune, to_cap = request.estimate, request.prune, request.to_cap
        runs = [
            self.model.start(
                j,
                k=self.stiffness,
                d=d,
                depth=self.depth,
                dt=self.dt,
                **settle_criterion(self.problem, self.case_settle(j)),
            )  # fmt: skip
            for j in range(self.cases)
        ]
        work = 0
        # Each free thread takes a piece of the case that has taken the fewest steps (so 3
        # cases keep 2 threads busy), until every case is done or a milestone decides. No case
        # runs more than a piece past the milestone still to be decided: a case slowed down by
        # a busy machine holds the others there, so a d that loses costs the same work however
        # the threads are scheduled.
        running: dict[Future[tuple[int, float]], DynamicRun] = {}
        milestone = CHUNK
        verdict = Verdict("running")
        while True:
            if pending and time.monotonic() - looked >= LOOK:
                assert resolve is not None
                looked = time.monotonic()
                named = resolve()
                if named is not None:  # the pieces under way end first: then nothing moves
                    for future in running:
                        work += _spent(future)
                    running.clear()
                    if named.get("caps", caps) is None:  # the search will not ask for it
                        dropped: list[DynamicRun | CaseRun] = list(runs)
                        return dropped, Verdict("dropped"), work
                    budget = named.get("budget", budget)
                    caps, pending = list(named.get("caps", caps)), False
            # (a run past a cap named later, as it stood at that cap)
            seen = [_capped(r, c) for r, c in zip(runs, caps, strict=True)]
            stopped = [r.finished or r.steps >= c for r, c in zip(seen, caps, strict=True)]
            while verdict.outcome == "running" and not pending:
                if all(stopped) and all(r.steps < milestone for r in seen):
                    break  # every case ended before this milestone
                if not all(e or r.steps >= milestone for e, r in zip(stopped, seen, strict=True)):
                    break  # a case has not reached it yet
                verdict = verdict_at(
                    seen, caps, milestone, budget, estimate=estimate, prune=prune, to_cap=to_cap
                )
                milestone += CHUNK
            waiting = [
                (r, c) for r, c, e in zip(runs, caps, stopped, strict=True)
                if not e and r not in running.values()
                and r.steps < (HOLD if pending else milestone + CHUNK)
            ]  # fmt: skip
            while waiting and verdict.outcome == "running" and len(running) < self.threads:
                r, c = min(waiting, key=lambda rc: rc[0].steps)
                waiting.remove((r, c))
                running[self.pool.submit(_timed_piece, r, min(CHUNK, c - r.steps))] = r
            if not running and pending:  # every case has ended or waits: wait for the names
                time.sleep(LOOK)
                continue
            if not running:
                if verdict.outcome == "running":
                    verdict = Verdict("done")
                return seen, verdict, work
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                work += _spent(future)
                del running[future]

    def close(self) -> None:
        self.pool.shutdown()


@dataclass
class Verdict:
    """How a d's runs ended: ``done`` (every case settled, diverged or reached its cap),
    ``failed`` (a case diverged or reached its cap unsettled), ``lost`` (it cannot win;
    ``total``: the steps it would take at least, from its steps and predictions at the
    deciding milestone), ``settles`` (every case predicted within its cap) or ``dropped`` (a
    request run ahead whose caps were named None: the search will not make it).
    ``predicted``: each case's predicted steps (:func:`predicted_steps`) when the decision
    came from them."""

    outcome: str
    total: float = 0.0
    predicted: tuple[float, ...] = ()


def predicted_steps(run: DynamicRun | CaseRun, at: int | None = None) -> float:
    """The steps ``run`` will have taken when it settles, predicted from the decay of its
    residual up to step ``at`` (None: its steps so far): the envelope (largest sample) over the
    last CHUNK steps against that over the CHUNK steps before, extrapolated exponentially down
    to the settle force. Its steps if it finished by then; ``at`` before PREDICT_AFTER, or
    when the run never settles (settle force 0), no prediction: ``at`` itself; inf when the
    envelope does not decay."""
    at = run.steps if at is None else at
    if run.finished and run.steps <= at:
        return float(run.steps) if not run.diverged else math.inf
    if at < PREDICT_AFTER or run.settle_force <= 0:
        return float(at)
    last = [r for n, r in run.history if at - CHUNK < n <= at]
    before = [r for n, r in run.history if at - 2 * CHUNK < n <= at - CHUNK]
    if not last or not before:
        return float(at)
    e1, e2 = max(before), max(last)
    if not (0 < e2 < e1):
        return math.inf
    rate = math.log(e1 / e2) / CHUNK
    return at + max(math.log(e2 / run.settle_force), 0.0) / rate


def verdict_at(
    runs: Sequence[DynamicRun | CaseRun],
    caps: list[int],
    at: int,
    budget: int | None,
    *,
    estimate: bool,
    prune: float = PRUNE,
    to_cap: bool = False,
) -> Verdict:
    """The d's verdict at milestone ``at`` (every case ended or past it): ``failed`` if a case
    diverged or reached its cap unsettled by ``at``; ``lost`` if the steps taken up to ``at``
    add up to ``budget``, or (past PREDICT_AFTER) a case is predicted past PRUNE times its cap
    or the predicted total past ``prune`` times ``budget``; ``settles`` (with ``estimate``) if
    every case settled within its cap or is predicted within it; else ``running``."""
    if any(
        (r.diverged and r.steps <= at) or (not r.finished and c <= at and r.steps >= c)
        for r, c in zip(runs, caps, strict=True)
    ):
        return Verdict("failed")
    taken = sum(min(r.steps, at) for r in runs)
    if budget is not None and taken >= budget:
        return Verdict("lost", float(taken))
    if at < PREDICT_AFTER:
        return Verdict("running")
    predicted = tuple(predicted_steps(r, at) for r in runs)
    total = float(sum(predicted))
    if not to_cap and any(p > PRUNE * c for p, c in zip(predicted, caps, strict=True)):
        return Verdict("lost", total, predicted)
    if budget is not None and total > prune * budget:
        return Verdict("lost", total, predicted)
    if estimate and all(p <= c for p, c in zip(predicted, caps, strict=True)):
        return Verdict("settles", total, predicted)
    return Verdict("running")


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
) -> DampingFit:
    """The d in ``bounds`` that settles every load case in the fewest total steps.

    Args:
        problem: the problem (settle_tolerance, and max_steps unless given, from its spec).
        stiffness: the model's :class:`~fpm.model.forces.Stiffness`
            (:func:`fpm.model.stiffness.model_stiffness`), or (S,) per-spring stiffness, N/m.
        dt: the time step, s; None = the spec's (resolved at ``stiffness`` for 'auto').
        depth: penetration depth (None = every layer).
        bounds: (low, high) for d, N s/m.
        guesses: two estimates of d to start from when there is no ``prediction`` (e.g.
            :func:`critical_damping` of the static and of the inertia-loaded shapes; equal
            when only one is known), clipped into the bounds.
        progress: called with {"d", "total_steps"} after each d tried.
        prediction: the fastest d predicted from the modes (:mod:`fpm.dynamics.modes`): the
            search starts there and confirms it.
        models: the reduced steps the prediction came from (one per load case): the margin
            starts from their estimate of it.
        max_steps: each run's cap on steps (None: the spec's; its 'auto' without a prediction
            is :data:`fpm.dynamics.modes.FALLBACK_STEPS`, repeated as ``auto`` says).
        auto: the cap came from fpm.max_steps 'auto': if nothing settles within it, the search
            is repeated with MAX_STEPS_GROWTH times the cap (RETRIES times at most).
        spread: runs the predicted d's load cases, each on its own, and the d tried next
            over other processes (:class:`Spread`; None: here); the answer is the same
            whatever runs them.
        settle: each load case's settle stiffness, N/m: its runs settle on the distance
            criterion (:mod:`fpm.dynamics.settle`); None: on the force criterion.

    Raises:
        DampingError: no d in the bounds settles every load case within max_steps.
    """
    if max_steps is None:
        value = problem.spec.fpm.max_steps
        auto = auto or value == "auto"
        max_steps = FALLBACK_STEPS if value == "auto" else int(value)
    step = time_step(problem, stiffness) if dt is None else dt
    for attempt in range(RETRIES + 1):
        last = not auto or attempt == RETRIES or max_steps >= SCHEMA_MAX_STEPS
        runs = _Runs(problem, stiffness, depth, step, spread, settle=settle)
        runs.max_steps = max_steps
        try:
            return _search(
                runs, bounds, guesses, progress, prediction, models, explain=last, grow=not last
            )
        except _ShortCap as short:  # the predicted d's runs need more steps than the cap
            need = short.args[0]
        except DampingError:
            if last:
                raise
            need = 0.0
        finally:
            runs.close()
        max_steps = int(min(SCHEMA_MAX_STEPS, max(MAX_STEPS_GROWTH * max_steps, 1.5 * need)))
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
) -> DampingFit:
    """The search (:func:`fastest_damping`); ``explain``: a failure says what would work (one
    probe run of up to PROBE_STEPS times max_steps), else it only says that nothing settled;
    ``grow``: the cap may grow (fpm.max_steps 'auto'), so if the predicted d's runs reach it
    unsettled, :class:`_ShortCap` says how many steps they need (their decay's prediction)
    at once, rather than searching on under a cap that is too small."""
    lo, hi = round(math.log(bounds[0]), 12), round(math.log(bounds[1]), 12)
    max_steps = runs.max_steps
    steps: dict[float, list[int] | None] = {}  # log d -> steps per case (None: not settled)
    slower: dict[float, int] = {}  # log d -> steps taken when stopped (at least the best total)
    # log d -> predicted steps per case, for a d stopped on its prediction
    forecast: dict[float, tuple[float, ...]] = {}
    # [log d, displacements (L, N, 3), residuals (L,) N] of the fewest total steps so far
    best: list[Any] = []
    short: dict[float, float] = {}  # log d -> steps it needs, for a d stopped by the cap

    def key(y: float) -> float:
        """log d within the bounds, rounded: one key per d, whatever path computed it."""
        return round(min(max(y, lo), hi), 12)

    def total(
        y: float, prune: float = PRUNE, to_cap: bool = False, beside: Sequence[Request] = ()
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
            elif budget is None and verdict.outcome in ("lost", "failed"):
                steps[y] = None
                if not any(r.diverged for r in results):  # stopped by the cap
                    short[y] = max([*verdict.predicted, 2.0 * max_steps])
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
        step = math.log(CONFIRM)
        left, mid, right = max(y0 - step, lo), y0, min(y0 + step, hi)
        caps = (max_steps,) * runs.cases
        sides = [y for y in dict.fromkeys(key(y) for y in (left, right)) if y != key(mid)]
        # Where other workers are free they run beside the predicted d's, their budget (its
        # total) named once those have ended; so do the margin's probes should it stay the
        # fastest, their caps named from its steps (:func:`_smallest_settling`).
        beside = [Request(math.exp(y), caps, LATER, prune=CONFIRM_PRUNE) for y in sides]
        edge = (
            None if models is None else _predicted_edge(models, math.exp(key(mid)), lo, max_steps)
        )
        if edge is not None:
            beside += [
                Request(math.exp(y), caps, None, estimate=True, caps_later=True)
                for y in _first_probes(edge, lo, math.log(BRACKET_STEP)) if y < key(mid)
            ]  # fmt: skip
        # The predicted d runs to the cap: early in a long run its decay is no guide (on a
        # slender bar it predicted 3-8 times the steps the run took).
        f_mid = total(mid, to_cap=True, beside=beside)
        if grow and key(mid) in short:
            raise _ShortCap(short[key(mid)])
        # Both at once where other workers are free (unless run beside): right's budget is
        # mid's total unless left turns out faster (then right runs anew, with left's).
        budget = _total(steps[best[0]]) if best else None
        runs.prefetch(
            [
                Request(math.exp(y), caps, budget, prune=CONFIRM_PRUNE)
                for y in sides if y not in steps and y not in slower
            ]
        )  # fmt: skip
        f_left, f_right = total(left, CONFIRM_PRUNE), total(right, CONFIRM_PRUNE)
    else:
        # Bracket: start from the two guesses and their geometric mean.
        g_low, g_high = sorted(min(max(math.log(g), lo), hi) for g in guesses)
        y0 = (g_low + g_high) / 2
        step = max((g_high - g_low) / 2, math.log(BRACKET_STEP))
        left, mid, right = max(y0 - step, lo), y0, min(y0 + step, hi)
        f_mid, f_left, f_right = total(mid), total(left), total(right)
    # Walk towards fewer steps, each step 1.6x longer than the last, until the fewest are
    # bracketed.
    walk = step
    while f_left < f_mid and left > lo:
        walk *= WALK_GROWTH
        right, f_right, mid, f_mid = mid, f_mid, left, f_left
        left = max(mid - walk, lo)
        f_left = total(left)
    while f_right < f_mid and right < hi:
        walk *= WALK_GROWTH
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
                + (": " + _what_would_work(runs, math.exp(y0), max_steps) if explain else "")
            )
    # Refine: golden-section steps between the best d and its tried neighbours.
    for _ in range(REFINE_STEPS):
        if _flat(steps, best[0]):
            break
        y = _next_point([*steps, *slower], best[0])
        if y is None:
            break
        total(y)
    y_best, displacements, residuals = best
    edge = None
    if models is not None:
        edge = _predicted_edge(models, math.exp(y_best), lo, max_steps)
    return DampingFit(
        d=math.exp(y_best),
        steps=list(steps[y_best] or []),
        displacements=displacements,
        d_min=math.exp(
            _smallest_settling(
                runs, steps, forecast, y_best, lo, max_steps, math.log(BRACKET_STEP), edge
            )
        ),
        guess=math.exp(y0),
        runs=runs.count,
        work=runs.work,
        tried=sorted(
            [(math.exp(y), None if s is None else sum(s)) for y, s in steps.items()]
            + [(math.exp(y), None) for y in slower]
        ),
        predicted=None if prediction is None else prediction.d,
        predicted_steps=[] if prediction is None else list(prediction.steps),
        max_steps=max_steps,
        residuals=[float(r) for r in residuals],
    )


def _predicted_edge(models: list[StepModel], d_best: float, lo: float, cap: int) -> float | None:
    """log d of the reduced steps' estimate of the margin: the smallest d (by bisection on log
    d, to 1%) whose predicted steps stay within MARGIN_CAP times their own at ``d_best`` in
    every load case; None if they do not settle at ``d_best``."""
    fastest = [m.steps(d_best, cap) for m in models]
    if not all(math.isfinite(f) and f > 0 for f in fastest):
        return None
    caps = [MARGIN_CAP * f for f in fastest]

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


def _total(steps: list[int] | None) -> int:
    return sum(steps) if steps is not None else 1 << 62


def _flat(steps: dict[float, list[int] | None], y_best: float) -> bool:
    """The best d's two tried neighbours both settled within FLAT of its total steps: a d between
    them could gain at most that, not worth a run."""
    tried = sorted(steps)
    i = tried.index(y_best)
    neighbours = [steps[y] for y in tried[max(i - 1, 0) : i] + tried[i + 1 : i + 2]]
    best = _total(steps[y_best])
    return len(neighbours) == 2 and all(
        n is not None and _total(n) <= (1 + FLAT) * best for n in neighbours
    )


def _next_point(tried: list[float], y_best: float) -> float | None:
    """Where to look next (log d): a golden-section step into the wider of the gaps between the
    best d and its tried neighbours (every other tried d is slower, stopped at the best total,
    or does not settle), or None once both gaps are below RESOLUTION."""
    tried = sorted(tried)
    i = tried.index(y_best)
    neighbours = tried[max(i - 1, 0) : i] + tried[i + 1 : i + 2]
    gaps = [n - y_best for n in neighbours]
    if not gaps:
        return None
    wide = max(gaps, key=abs)
    if abs(wide) < 2 * math.log(RESOLUTION):
        return None
    return y_best + GOLDEN * wide


def _smallest_settling(
    runs: _Runs,
    steps: dict[float, list[int] | None],
    forecast: dict[float, tuple[float, ...]],
    y_best: float,
    lo: float,
    max_steps: int,
    step: float,
    edge: float | None = None,
) -> float:
    """log d of the smallest d whose runs all settle within MARGIN_CAP times their steps at the
    fastest d. The d tried by the search answer first, from their settled steps or from the
    predictions they were stopped on (``forecast``): from the smallest that settles, the
    largest below it that does not brackets the edge. With ``edge`` (log d; the reduced
    steps' estimate) the probes of :func:`_first_probes` come next: ``step / 2`` below it,
    and if that settles the walk goes on from there (its next step was run at once where
    workers are free), else the edge itself is probed. Without a bracket the walk goes down
    by ``step`` while d settles; bisection narrows the bracket to ``step / 2`` (log); with an
    ``edge`` at most MARGIN_PROBES probes in all (d_min is then the smallest d found that
    settles). A probe stops once its decay predicts the answer (past PREDICT_AFTER steps):
    d_min is an estimate where runs are long, exact where they settle sooner."""
    fastest = steps[y_best] or []
    caps = [min(max_steps, MARGIN_CAP * s) for s in fastest]

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

    if edge is not None:
        first = _first_probes(edge, lo, step)
        first = [y for y in first if open_(y)] if open_(first[0]) else []
        # At once where other workers are free (the second wasted if the first does not
        # settle): the walk's next step from there.
        runs.prefetch(
            [Request(math.exp(y), tuple(caps), None, estimate=True)
             for y in first if answers.get(y) is None]
        )  # fmt: skip
        if first and settles(first[0]):
            y_ok = first[0]
        elif first:
            y_fail = first[0]
            edge = round(edge, 12)
            if open_(edge):  # below the edge did not settle: the edge itself
                if settles(edge):
                    y_ok = edge
                else:
                    y_fail = edge
    limit = MARGIN_PROBES if edge is not None else math.inf
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


def _first_probes(edge: float, lo: float, step: float) -> list[float]:
    """log d of the margin's first probes from the reduced steps' edge (log d;
    :func:`_smallest_settling`): ``step / 2`` below it and the walk's next ``step`` below
    that (within ``lo``); the edge itself where it is ``lo``. Where the first settles, every d
    between it and the fastest is taken to settle too (the runs settle the sooner the nearer
    the fastest d, as on every organ measured), so the edge is not run: on the 93,705-node
    organ (the reduced edge 12-40% high) that saved a probe of 20 CPU s. Where it does not
    (the organ at 3 and 5 mm: the edge itself is the margin), the edge is probed next: the
    same two probes in one process as edge-first, one more in a row where workers ran the
    first two at once."""
    edge = round(edge, 12)
    below = round(max(edge - step / 2, lo), 12)
    further = round(max(below - step, lo), 12)
    if below >= edge:
        return [edge]
    return [below, further] if further < below else [below]


PROBE_STEPS = 20
"""When nothing settles, the probe run may take this many times max_steps (capped at the
schema's 1,000,000) to measure the steps a run needs."""


def _what_would_work(runs: _Runs, d: float, max_steps: int) -> str:
    """Numbers for a run that cannot settle: the dt 'auto' would take (half the stability
    estimate, at most 1 ms) and the steps a run at d needs there, measured by one probe of up to
    PROBE_STEPS x max_steps steps per load case."""
    p = runs.problem
    dt = min(runs.dt, auto_time_step(p, runs.stiffness))
    cap = min(1_000_000, PROBE_STEPS * max_steps)
    probe = _Runs(p, runs.stiffness, runs.depth, dt)
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
    """No d in the bounds settles every load case."""


class _ShortCap(Exception):
    """The predicted d's runs reached the cap unsettled; ``args[0]``: the steps they need."""
