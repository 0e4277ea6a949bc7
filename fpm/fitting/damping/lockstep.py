"""The d search's runs: every load case at one d advanced in lockstep pieces of ``chunk``
steps on threads (:class:`_Runs`), a :class:`Verdict` taken at each milestone every case has
passed (:func:`verdict_at`): lost, settled, or running on. Decisions read only each case's own
state at the milestone, so a search repeats exactly however the threads interleave, and a case
run on its own by another process (:func:`run_case`) replays to the same verdict
(:func:`replay_verdict`). docs/explanation/service/many-workers.md says how they spread."""

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

from ...dynamics.settle import run_criterion
from ...dynamics.simulation import DynamicRun, FpmModel
from ...dynamics.step_caps import fixed_max_steps
from ...dynamics.voigt import DIVERGED, INVERTED, RUNNING, SETTLED
from ...model.forces import Stiffness
from ...model.problem import Problem
from .settings import DEFAULT, DampingSettings


def _piece(run: DynamicRun, steps: int, settings: DampingSettings = DEFAULT) -> int:
    """Advance ``run`` by ``steps`` in samples of ``settings.sample``; the steps taken."""
    start, sample = run.steps, settings.sample
    while run.steps - start < steps and not run.advance(min(sample, steps - run.steps + start)):
        pass
    return run.steps - start


def _timed_piece(run: DynamicRun, steps: int, settings: DampingSettings) -> tuple[int, float]:
    """:func:`_piece` on a pool thread: (the steps taken, the CPU seconds that thread spent)."""
    cpu = time.thread_time()
    return _piece(run, steps, settings), time.thread_time() - cpu


_LOCKSTEP_CPU = threading.local()


def lockstep_cpu() -> float:
    """CPU seconds the lockstep runs started from this thread have spent on the pool's threads
    so far (added to the thread's own ``time.thread_time()``: what a request run here cost)."""
    return float(getattr(_LOCKSTEP_CPU, "seconds", 0.0))


def _spent(future: Future[tuple[int, float]]) -> int:
    """A piece's steps; its CPU seconds counted for the thread that started the lockstep."""
    steps, cpu = future.result()
    _LOCKSTEP_CPU.seconds = lockstep_cpu() + cpu
    return steps


@dataclass
class CaseRun:
    """One load case run on its own to its end (settled, diverged, or ``cap`` steps), as the
    search reads it. JSON-able but for ``displacements`` (raw float64 bytes in transit).

    Attributes:
        steps: time steps taken; state: voigt.RUNNING (reached its cap), SETTLED or DIVERGED
            (or INVERTED); settle_force: the residual it settles below, N.
        history: (steps, residual N) after every ``sample`` steps.
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
        moved = run.result().displacements if run.state == SETTLED else np.zeros((0, 3))
        return cls(run.steps, run.state, run.settle_force, list(run.history), moved)


@dataclass(frozen=True)
class Request:
    """One d's lockstep runs as the search asks for them (:meth:`_Runs.__call__`'s arguments):
    d (N s/m), each case's cap, the budget (None: none), how predictions decide;
    ``caps_later``: the caps are named once the runs have started, within ``caps`` (a margin
    probe run beside the predicted d's)."""

    d: float
    caps: tuple[int, ...]
    budget: int | None
    estimate: bool = False
    prune: float = DEFAULT.prune
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
    static: np.ndarray | None = None,
    distance: float | None = None,
    *,
    settings: DampingSettings = DEFAULT,
) -> CaseRun:
    """Load case ``load_case`` at (``stiffness``, ``d`` N s/m, ``depth``, ``dt`` s) from rest
    to its end (settled, diverged or ``cap`` steps), in the same pieces as :class:`_Runs`, so
    the same floating-point sequence in any process. ``settle_stiffness`` (N/m), ``static``
    (N, 3) m and ``distance``: its settle criterion (:func:`fpm.dynamics.settle.run_criterion`)."""
    run = model.start(
        load_case, k=stiffness, d=d, depth=depth, dt=dt,
        settle=run_criterion(model.problem.spec, settle_stiffness, static, distance),
    )  # fmt: skip
    while not run.finished and run.steps < cap:
        _piece(run, min(settings.chunk, cap - run.steps), settings)
    return CaseRun.of(run)


Resolve = Callable[[], dict[str, Any] | None]
"""Where a lockstep learns the caps named later (None: not yet): {"caps": [int per case], or
None: drop the request} (:func:`named_later`)."""


def run_request(
    problem: Problem,
    stiffness: Stiffness | np.ndarray,
    depth: int | None,
    dt: float,
    request: Request,
    resolve: Resolve | None = None,
    settle: Sequence[float] | None = None,
    targets: np.ndarray | None = None,
    distances: Sequence[float] | None = None,
) -> Outcome:
    """One d's lockstep runs (:meth:`_Runs.locked`) in this process, for another's search;
    ``resolve``: where what is named later comes from; the rest as :class:`_Runs` takes them."""
    runs = _Runs(problem, stiffness, depth, dt, settle=settle, targets=targets, distances=distances)
    try:
        return runs.locked(request, resolve)
    finally:
        runs.close()


def settled_total(runs: list[CaseRun], caps: list[int]) -> int | None:
    """The total steps of a d whose cases each ran on their own to their end, where the search
    would take it for the best so far, else None."""
    if replay_verdict(runs, caps).outcome == "done" and all(r.state == SETTLED for r in runs):
        return sum(r.steps for r in runs)
    return None


def named_later(
    request: Request,
    runs: list[CaseRun],
    caps: list[int],
    settings: DampingSettings = DEFAULT,
) -> dict[str, Any]:
    """What a margin probe ``request``, run beside a d's cases (``runs``, each to ``caps``),
    learns once they have ended, as the search would make it: its caps, ``margin_cap`` times
    each case's steps within its own (None where they did not all settle:
    :func:`settled_total`)."""
    if settled_total(runs, caps) is None:
        return {"caps": None}
    cap = settings.margin_cap
    return {"caps": [min(c, cap * r.steps) for r, c in zip(runs, request.caps, strict=True)]}


def _capped(run: DynamicRun, cap: int) -> DynamicRun | CaseRun:
    """``run`` as it stood at ``cap`` steps (a run that went on past a cap named later)."""
    if run.steps <= cap:
        return run
    return CaseRun(cap, RUNNING, run.settle_force, [(n, r) for n, r in run.history if n <= cap])


class Spread(Protocol):
    """How the search's runs may be spread over other processes
    (:class:`worker.spread.CaseSpread`); the runs, and so the answer, are the same."""

    def separate(
        self,
        d: float,
        caps: list[int],
        local: Callable[[int, float, int], CaseRun],
        beside: list[Request],
        local_request: Callable[[Request, Resolve], Outcome],
    ) -> tuple[list[CaseRun], list[Outcome | None]]:
        """Every load case of one d run on its own to its end (``local(j, d, cap)`` runs case j
        here) and, where other workers are free, the requests ``beside`` at the same time,
        learning what :func:`named_later` makes of the cases' runs: their outcomes in order
        (None: not run), ``local_request`` running one here."""
        ...

    def ahead(
        self, requests: list[Request], local: Callable[[Request], Outcome]
    ) -> list[Outcome | None]:
        """Requests the search will probably make next, at once: their outcomes in order (None:
        not run), ``local`` running one here."""
        ...


def replay_verdict(
    runs: list[CaseRun], caps: list[int], settings: DampingSettings = DEFAULT
) -> Verdict:
    """The verdict the lockstep runs reach for a d run to its cap with no budget, replayed from
    its cases run each to its end: the milestones in turn until one decides ``failed``, else
    ``done``."""
    verdict, milestone = Verdict("running"), settings.chunk
    while verdict.outcome == "running" and not all(r.steps < milestone for r in runs):
        verdict = verdict_at(runs, caps, milestone, None, estimate=False, to_cap=True,
                             settings=settings)  # fmt: skip
        milestone += settings.chunk
    return Verdict("done") if verdict.outcome == "running" else verdict


class _Runs:
    """Runs every load case at one d, in pieces, on threads (the kernel releases the GIL).

    ``spread``: runs the predicted d's cases and the d tried next over other processes (None:
    here, nothing ahead). ``settle`` (L,) N/m, ``targets`` (L, N, 3) m and ``distances`` (L,):
    the runs' settle criterion (:func:`fpm.dynamics.settle.run_criterion`)."""

    def __init__(
        self,
        problem: Problem,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        dt: float,
        spread: Spread | None = None,
        *,
        settle: Sequence[float] | None = None,
        targets: np.ndarray | None = None,
        distances: Sequence[float] | None = None,
        settings: DampingSettings = DEFAULT,
    ):
        self.problem = problem
        self.settings = settings
        self.settle = None if settle is None else [float(s) for s in settle]
        self.targets = targets if distances is not None else None
        self.distances = None if distances is None else [float(s) for s in distances]
        self.stiffness, self.depth, self.dt = stiffness, depth, dt
        self.model = FpmModel(problem)
        self.cases = len(problem.load_cases)
        self.threads = min(self.cases, os.cpu_count() or 1)
        self.pool = ThreadPoolExecutor(self.threads)
        self.count, self.work = 0, 0  # runs made and steps taken, once the search takes them
        self.max_steps = fixed_max_steps(problem.spec.fpm.max_steps)  # each run's cap on steps
        self.spread = spread
        self.fetched: dict[Request, Outcome] = {}

    def local(self, load_case: int, d: float, cap: int) -> CaseRun:
        """Load case ``load_case`` at d run on its own to its end in this process."""
        return run_case(
            self.model, self.stiffness, self.depth, self.dt, load_case, d, cap,
            self.case_settle(load_case), *self.case_target(load_case), settings=self.settings,
        )  # fmt: skip

    def case_settle(self, load_case: int) -> float | None:
        """Load case ``load_case``'s settle stiffness, N/m (None: the force criterion)."""
        return None if self.settle is None else self.settle[load_case]

    def case_target(self, load_case: int) -> tuple[np.ndarray | None, float | None]:
        """Load case ``load_case``'s static equilibrium, (N, 3) m, and settle distance (None,
        None: the runs do not settle towards it)."""
        if self.targets is None or self.distances is None:
            return None, None
        return self.targets[load_case], self.distances[load_case]

    def separate(
        self, d: float, caps: list[int], beside: Sequence[Request] = ()
    ) -> tuple[list[CaseRun], Verdict]:
        """Every load case at d, each run on its own to its end, and the verdict the lockstep would
        reach (:func:`replay_verdict`): for a d with no budget run to the cap, the same as
        :meth:`__call__` but that a failed d's other cases also run to their end.
        ``beside``: margin probes run at the same time by ``spread`` (their caps named from
        this d's runs), kept as :meth:`prefetch` keeps them."""
        if self.spread is None:
            runs = list(self.pool.map(self.local, range(self.cases), [d] * self.cases, caps))
        else:
            runs, outcomes = self.spread.separate(d, caps, self.local, list(beside), self.locked)
            for request, outcome in zip(beside, outcomes, strict=True):
                named = named_later(request, runs, caps, self.settings)
                if named["caps"] is not None:
                    taken = replace(request, caps=tuple(named["caps"]), caps_later=False)
                    self._keep([taken], [outcome])
        self.count += self.cases
        self.work += sum(r.steps for r in runs)
        return runs, replay_verdict(runs, caps, self.settings)

    def prefetch(self, requests: list[Request]) -> None:
        """Run ``requests`` at once by ``spread`` (none without it), for the calls that make the
        very same requests."""
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
        """``request``'s lockstep runs here, as :class:`CaseRun`, not counted until the search
        takes them; their pool threads' CPU seconds credited to this thread."""
        runs, verdict, _ = self._lockstep(request, resolve)
        return [CaseRun.of(run) for run in runs], verdict

    def __call__(
        self,
        d: float,
        caps: list[int],
        budget: int | None = None,
        *,
        estimate: bool = False,
        prune: float = DEFAULT.prune,
        to_cap: bool = False,
    ) -> tuple[Sequence[DynamicRun | CaseRun], Verdict]:
        """Every load case at d, case j for at most ``caps[j]`` steps, until every case has
        settled, one has diverged or reached its cap unsettled, or a milestone's
        :func:`verdict_at` decides (``budget``: a d is lost once its steps add up to it;
        ``prune``: or its predicted total exceeds this times it; ``to_cap``: a case runs on to
        its cap whatever its decay predicts; ``estimate``: it settles once every case is
        predicted within its cap). A request run ahead (:meth:`prefetch`) is taken from there."""
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
        """:meth:`__call__`'s runs of ``request``, and the steps they took. Until caps named
        later are named (``resolve``, looked at every ``settings.look`` s) the cases
        run on undecided up to ``settings.hold`` steps; the milestones passed are then decided
        in turn as they would have been, so the verdict is the same."""
        d, caps, budget = request.d, list(request.caps), request.budget
        pending = request.caps_later
        if pending and resolve is None:
            raise ValueError("what is named later needs where to learn it")
        looked = -math.inf
        estimate, prune, to_cap = request.estimate, request.prune, request.to_cap
        settings = self.settings
        chunk, look = settings.chunk, settings.look
        runs = [
            self.model.start(
                j,
                k=self.stiffness,
                d=d,
                depth=self.depth,
                dt=self.dt,
                settle=run_criterion(self.problem.spec, self.case_settle(j), *self.case_target(j)),
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
        milestone = chunk
        verdict = Verdict("running")
        while True:
            if pending and time.monotonic() - looked >= look:
                assert resolve is not None
                looked = time.monotonic()
                named = resolve()
                if named is not None:  # the pieces under way end first: then nothing moves
                    for future in running:
                        work += _spent(future)
                    running.clear()
                    if named["caps"] is None:  # the search will not ask for it
                        dropped: list[DynamicRun | CaseRun] = list(runs)
                        return dropped, Verdict("dropped"), work
                    caps, pending = list(named["caps"]), False
            # (a run past a cap named later, as it stood at that cap)
            seen = [_capped(r, c) for r, c in zip(runs, caps, strict=True)]
            stopped = [r.finished or r.steps >= c for r, c in zip(seen, caps, strict=True)]
            while verdict.outcome == "running" and not pending:
                if all(stopped) and all(r.steps < milestone for r in seen):
                    break  # every case ended before this milestone
                if not all(e or r.steps >= milestone for e, r in zip(stopped, seen, strict=True)):
                    break  # a case has not reached it yet
                verdict = verdict_at(
                    seen, caps, milestone, budget, estimate=estimate, prune=prune, to_cap=to_cap,
                    settings=settings,
                )  # fmt: skip
                milestone += chunk
            waiting = [
                (r, c) for r, c, e in zip(runs, caps, stopped, strict=True)
                if not e and r not in running.values()
                and r.steps < (settings.hold if pending else milestone + chunk)
            ]  # fmt: skip
            while waiting and verdict.outcome == "running" and len(running) < self.threads:
                r, c = min(waiting, key=lambda rc: rc[0].steps)
                waiting.remove((r, c))
                piece = self.pool.submit(_timed_piece, r, min(chunk, c - r.steps), settings)
                running[piece] = r
            if not running and pending:  # every case has ended or waits: wait for the names
                time.sleep(look)
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
    ``total``: the steps it would take at least), ``settles`` (every case predicted within its
    cap) or ``dropped`` (a request whose caps were named None); ``predicted``: each case's
    predicted steps where they decided."""

    outcome: str
    total: float = 0.0
    predicted: tuple[float, ...] = ()


def predicted_steps(
    run: DynamicRun | CaseRun, at: int | None = None, settings: DampingSettings = DEFAULT
) -> float:
    """The steps ``run`` will have taken when it settles, from the decay of its residual up to
    step ``at`` (None: now): the envelope over the last ``chunk`` steps against the chunk
    before, extrapolated exponentially to the settle force. Its steps if it finished by then;
    ``at`` itself before ``predict_after`` or where it never settles; inf where the envelope
    does not decay."""
    at = run.steps if at is None else at
    if run.finished and run.steps <= at:
        return float(run.steps) if not run.diverged else math.inf
    chunk = settings.chunk
    if at < settings.predict_after or run.settle_force <= 0:
        return float(at)
    last = [r for n, r in run.history if at - chunk < n <= at]
    before = [r for n, r in run.history if at - 2 * chunk < n <= at - chunk]
    if not last or not before:
        return float(at)
    e1, e2 = max(before), max(last)
    if not (0 < e2 < e1):
        return math.inf
    rate = math.log(e1 / e2) / chunk
    return at + max(math.log(e2 / run.settle_force), 0.0) / rate


def verdict_at(
    runs: Sequence[DynamicRun | CaseRun],
    caps: list[int],
    at: int,
    budget: int | None,
    *,
    estimate: bool,
    prune: float = DEFAULT.prune,
    to_cap: bool = False,
    settings: DampingSettings = DEFAULT,
) -> Verdict:
    """The d's verdict at milestone ``at`` (every case ended or past it): ``failed``, ``lost``
    (the steps taken add up to ``budget``, or past ``predict_after`` a case is predicted past
    ``settings.prune`` times its cap or the total past ``prune`` times ``budget``),
    ``settles`` (with ``estimate``, every case within its cap) or ``running``."""
    if any(
        (r.diverged and r.steps <= at) or (not r.finished and c <= at and r.steps >= c)
        for r, c in zip(runs, caps, strict=True)
    ):
        return Verdict("failed")
    taken = sum(min(r.steps, at) for r in runs)
    if budget is not None and taken >= budget:
        return Verdict("lost", float(taken))
    if at < settings.predict_after:
        return Verdict("running")
    predicted = tuple(predicted_steps(r, at, settings) for r in runs)
    total = float(sum(predicted))
    if not to_cap and any(p > settings.prune * c for p, c in zip(predicted, caps, strict=True)):
        return Verdict("lost", total, predicted)
    if budget is not None and total > prune * budget:
        return Verdict("lost", total, predicted)
    if estimate and all(p <= c for p, c in zip(predicted, caps, strict=True)):
        return Verdict("settles", total, predicted)
    return Verdict("running")
