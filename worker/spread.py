"""The damping stage's runs spread over the free workers.

The d search's dearest runs are the predicted d's, every load case run to its end
(docs/explanation/physics/damping-search.md, *Confirmation*): each case's run is independent of
the others' (:func:`fpm.fitting.damping.lockstep.run_case`). Then come the d that confirm it, where
the reduced steps cannot rule them out, and the margin's probes, each a d's lockstep runs whose
requests the search can name before it needs them
(:meth:`fpm.fitting.damping.lockstep._Runs.prefetch`). The damping job hands them out as tasks:

- each task (the plan, and one load case at d with its cap, or one d's request) is stored
  under its digest (:func:`worker.tasks.task_digest`) and, when other workers are idle,
  enqueued as a :func:`damping_case` job on the priority queue (requests ahead only then);
- whoever claims a task first runs it (:func:`store.scratch.claim_case`): a case job on another
  worker, or the damping job itself on its own threads, which leaves the first tasks to the
  free workers (one each), takes the others in order, and after GRACE seconds any nobody
  claimed; a holder renews its claim while it runs, so a task whose holder died is claimed
  again once the claim expires (the damping job runs it; the killed job's retry finds it run);
- the runs are stored once (JSON and raw float64 displacements) and the damping job reads
  them back from there, in order.

A task's runs are a deterministic function of the task, and the search takes a request's
outcome only for the very request it makes, so the fitted parameters are the same to the bit
whoever runs which task, with 1, 2 or 3 workers, and after a worker died.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from functools import partial
from typing import Any

from redis import Redis
from rq import get_current_job
from rq.job import Job

from fpm.dynamics.simulation import FpmModel
from fpm.fitting.damping.choice import DampingPlan
from fpm.fitting.damping.lockstep import (
    CaseRun,
    Outcome,
    Request,
    Resolve,
    Verdict,
    named_later,
    run_case,
    run_request,
)
from fpm.fitting.damping.validation import Validation, validate
from fpm.model.stiffness import model_stiffness
from store import graph, keys, records, scratch
from store.text import escape

from . import memory
from .idle import free_workers, local_threads
from .problems import problem_of, reference_of
from .tasks import (
    from_stored,
    request_of,
    run_task,
    targets_of,
    task_clock,
    task_digest,
    task_name,
    validation_stored,
)

POLL = 0.1
"""Seconds between the damping job's looks at its tasks."""
GRACE = 2.0
"""Seconds the damping job leaves the tasks it handed out to the free workers before it runs
any of them that nobody has claimed (a free worker claims one within a fraction of that)."""


class CaseSpread:
    """The damping job's :class:`fpm.fitting.damping.lockstep.Spread`: its runs as tasks, handed to
    free workers and run here when nobody took them (the module docstring).

    Args:
        redis, calibration_id: where the tasks go.
        plan: the damping stage's :class:`DampingPlan` (the runs' stiffness, depth, dt).
        worker: this worker's name (spans, and the claims' holder with the process id).
        timeout: a case job's timeout, s.
        going_on: called while waiting; raises to stop (the calibration was canceled).

    Attributes:
        rounds: per hand-out: (Unix start, end, the tasks' span names).
        cpu: the CPU seconds of the tasks run here (counted in their own spans).
        first_cpu: the process's CPU seconds when the first hand-out began (None: none yet).
    """

    def __init__(
        self,
        redis: Redis,
        calibration_id: str,
        plan: DampingPlan,
        worker: str,
        timeout: int,
        going_on: Callable[[], None],
    ):
        self.redis, self.calibration_id, self.plan = redis, calibration_id, plan
        self.worker, self.timeout, self.going_on = worker, timeout, going_on
        self.holder = f"{worker}:{os.getpid()}"
        self.threads = os.cpu_count() or 1  # at most; :func:`local_threads` at the time
        self.rounds: list[tuple[float, float, list[str]]] = []
        self.cpu = 0.0
        self.first_cpu: float | None = None

    def _after(self) -> str:
        """The span the next hand-out's tasks wait for
        (:meth:`worker.jobs.spans._Span.add_around`)."""
        return "damping" if not self.rounds else f"damping ({len(self.rounds)})"

    def separate(
        self,
        d: float,
        caps: list[int],
        local: Callable[[int, float, int], CaseRun],
        beside: list[Request],
        local_request: Callable[[Request, Resolve], Outcome],
    ) -> tuple[list[CaseRun], list[Outcome | None]]:
        """Every load case at d as a task (run here when no other worker is free), and each
        request ``beside`` as a task after them, only when other workers are free: the caps
        they learn later are named in their tasks once the cases' runs are all stored."""
        after = self._after()
        free = free_workers(self.redis, self.worker, self.calibration_id)
        asked = beside if free else []
        specs = [
            {**asdict(self.plan), "d": d, "load_case": j, "cap": int(c), "after": after}
            for j, c in enumerate(caps)
        ] + [{**asdict(self.plan), "request": asdict(r), "after": after} for r in asked]
        tasks = [task_digest(spec) for spec in specs]
        runs: list[Callable[[], tuple[list[CaseRun], Verdict | None]]]
        runs = [partial(_one_case, local, j, d, int(c)) for j, c in enumerate(caps)]
        runs += [
            partial(_one_named_later, local_request, self._resolve(t), r)
            for t, r in zip(tasks[len(caps) :], asked, strict=True)
        ]

        def name_later() -> bool:
            """Once the cases' runs are all stored, the caps the requests learn from them, in
            their tasks."""
            cases = tasks[: len(caps)]
            if not all(scratch.has_case_run(self.redis, self.calibration_id, t) for t in cases):
                return False
            stored = [scratch.get_case_run(self.redis, self.calibration_id, t) for t in cases]
            ran = [from_stored(*found)[0][0] for found in stored if found is not None]
            for task, request in zip(tasks[len(caps) :], asked, strict=True):
                named = named_later(request, ran, caps)
                scratch.name_later(self.redis, self.calibration_id, task, named)
            return True

        later = set(range(len(caps), len(specs))) if asked else set()
        done = self._round(specs, runs, free, (name_later, later))
        outcomes: list[Outcome | None] = [None] * len(beside)
        for i, (found, verdict) in enumerate(done[len(caps) :]):
            assert verdict is not None  # a request's
            outcomes[i] = (found, verdict)
        return [found[0][0] for found in done[: len(caps)]], outcomes

    def ahead(
        self, requests: list[Request], local: Callable[[Request], Outcome]
    ) -> list[Outcome | None]:
        """Each request as a task, only when other workers are free (else none is run)."""
        free = free_workers(self.redis, self.worker, self.calibration_id)
        if not free:
            return [None] * len(requests)
        after = self._after()
        specs = [{**asdict(self.plan), "request": asdict(r), "after": after} for r in requests]
        done = self._round(specs, [partial(_one_request, local, r) for r in requests], free)
        return [None if verdict is None else (runs, verdict) for runs, verdict in done]

    def _claimed(self, task: str) -> bool:
        """Someone runs the task, or it has run."""
        return scratch.is_claimed(self.redis, self.calibration_id, task) or scratch.has_case_run(
            self.redis, self.calibration_id, task
        )

    def _resolve(self, task: str) -> Resolve:
        """Where request task ``task`` run here learns its caps named later."""
        return partial(scratch.named_later, self.redis, self.calibration_id, task)

    def _round(
        self,
        specs: list[dict[str, Any]],
        local: Sequence[Callable[[], tuple[list[CaseRun], Verdict | None]]],
        free: int,
        later: tuple[Callable[[], bool], set[int]] | None = None,
    ) -> list[tuple[list[CaseRun], Verdict | None]]:
        """Store the tasks ``specs``, hand them to ``free`` workers and run the rest here
        (``local[i]`` runs task i), wait for every one; their stored runs in order.
        ``later``: (called while waiting until it has named what requests learn later (True),
        those requests' tasks): this job starts those only once every other task is claimed
        (a request that waits for its name must not keep a thread from the runs it waits for).
        Here at most :func:`local_threads` tasks run at once, but a task the others wait for
        is always taken once nothing else here can run (its holder died, say)."""
        name_later, named_later = later if later is not None else (None, set())
        start = time.time()
        if self.first_cpu is None:
            self.first_cpu = time.process_time()
        tasks = [task_digest(s) for s in specs]
        for task, spec in zip(tasks, specs, strict=True):
            scratch.add_case_task(self.redis, self.calibration_id, task, spec)
        if free:
            self._enqueue(tasks, specs)
        handed = set(range(min(free, len(tasks))))  # the first ones; this job takes the rest
        enqueued = set(range(len(tasks))) if free else set()
        futures: dict[int, Future[float]] = {}
        with ThreadPoolExecutor(len(tasks)) as pool:
            while True:
                for i, future in list(futures.items()):
                    if future.done():
                        self.cpu += future.result()  # raises its error
                        del futures[i]
                waiting = [
                    i for i, t in enumerate(tasks)
                    if not scratch.has_case_run(self.redis, self.calibration_id, t)
                ]  # fmt: skip
                if not waiting:
                    break
                if name_later is not None and name_later():
                    name_later, named_later = None, set()
                if handed and time.time() > start + GRACE:
                    handed = set()  # not claimed by now: nobody took them
                first = [i for i in waiting if i not in named_later]
                ready = [  # in order: the longest runs (a d's cases) come first
                    i for i in waiting if i not in futures and i not in handed
                    and (i not in named_later or all(self._claimed(tasks[k]) for k in first))
                ]  # fmt: skip
                room = 0
                if ready:
                    queued = sum(
                        1 for i in waiting if i in enqueued and not self._claimed(tasks[i])
                    )  # an idle worker will take one
                    cores = local_threads(self.redis, self.worker, self.threads, queued)
                    room = cores - len(futures)
                # whatever runs here waits for its name: a task it waits for may go beyond room
                held = all(i in named_later for i in futures)
                for i in ready:
                    if room <= 0 and not (held and i not in named_later):
                        continue
                    if scratch.claim_case(self.redis, self.calibration_id, tasks[i], self.holder):
                        room -= 1
                        held = held and i in named_later
                        futures[i] = pool.submit(
                            run_task, self.redis, self.calibration_id, tasks[i], specs[i],
                            self.holder, self.worker, local[i], task_clock,
                        )  # fmt: skip
                self.going_on()
                time.sleep(POLL)
        done = []
        for task in tasks:
            stored = scratch.get_case_run(self.redis, self.calibration_id, task)
            assert stored is not None
            done.append(from_stored(*stored))
        self.rounds.append((start, time.time(), [task_name(s) for s in specs]))
        return done

    def _enqueue(self, tasks: list[str], specs: list[dict[str, Any]]) -> None:
        enqueue(self.redis, self.calibration_id, tasks, specs, self.timeout)


def enqueue(
    redis: Redis, calibration_id: str, tasks: list[str], specs: list[dict[str, Any]], timeout: int
) -> None:
    """A case job per task not run yet, on the priority queue (no failure callback: a case job
    that fails loses nothing, the damping job runs its task)."""
    record = records.get_calibration(redis, calibration_id)
    name = escape(record.name) if record is not None else calibration_id
    q = graph.priority_queue(redis)
    for task, spec in zip(tasks, specs, strict=True):
        if scratch.has_case_run(redis, calibration_id, task):
            continue
        q.enqueue_call(
            keys.CASE_JOB,
            args=(calibration_id, task),
            job_id=keys.case_job_id(calibration_id, task),
            timeout=timeout,
            result_ttl=600,
            failure_ttl=24 * 3600,
            description=f"{name}: {task_name(spec)}",
        )


class ValidationTask:
    """The damping job's :data:`fpm.fitting.damping.stage.Validator`: the validation cases'
    static solves as a task (like the d search's, the module docstring), handed to an idle
    worker when there is one (while this job finds the slowest modes the other workers are
    idle, and the solves' systems stay out of this job's memory: at 93,705 nodes about 0.9
    GB, its peak), else run here on a thread of its own, as is a task nobody claimed within
    GRACE or whose holder died. The answer is the same wherever it runs.

    Args:
        redis, calibration_id, worker, timeout: as :class:`CaseSpread`'s.
        local: ``local(theta, depth)`` solves them here
            (:func:`fpm.fitting.damping.validation.validate` of the job's problem and reference).

    Attributes:
        cpu: the CPU seconds of a validation run here (counted in its own span).
    """

    def __init__(
        self,
        redis: Redis,
        calibration_id: str,
        worker: str,
        timeout: int,
        local: Callable[[list[float], int | None], Validation],
    ):
        self.redis, self.calibration_id, self.worker = redis, calibration_id, worker
        self.timeout, self.local = timeout, local
        self.holder = f"{worker}:{os.getpid()}"
        self.cpu = 0.0

    def __call__(self, theta: list[float], depth: int | None) -> Future[Validation]:
        spec = {"validation": {"theta": [float(t) for t in theta], "depth": depth},
                "after": "damping"}  # fmt: skip
        task = task_digest(spec)
        scratch.add_case_task(self.redis, self.calibration_id, task, spec)
        handed = free_workers(self.redis, self.worker, self.calibration_id) > 0
        if handed:
            enqueue(self.redis, self.calibration_id, [task], [spec], self.timeout)
        pool = ThreadPoolExecutor(1, thread_name_prefix="validation")
        future = pool.submit(self._wait, task, spec, handed)
        pool.shutdown(wait=False)
        return future

    def _wait(self, task: str, spec: dict[str, Any], handed: bool) -> Validation:
        """The task's stored answer, once someone has run it (this thread, when nobody
        claimed it within GRACE of a hand-out, or its holder died)."""
        start = time.time()
        while not scratch.has_case_run(self.redis, self.calibration_id, task):
            if not handed or time.time() > start + GRACE:
                if scratch.claim_case(self.redis, self.calibration_id, task, self.holder):
                    theta, depth = spec["validation"]["theta"], spec["validation"]["depth"]
                    self.cpu += run_task(
                        self.redis, self.calibration_id, task, spec, self.holder, self.worker,
                        partial(self.local, theta, depth), time.thread_time, validation_stored,
                    )  # fmt: skip
                    continue
            time.sleep(POLL)
        found = scratch.get_case_run(self.redis, self.calibration_id, task)
        assert found is not None
        return Validation(**found[0]["validation"])


def _one_case(
    local: Callable[[int, float, int], CaseRun], j: int, d: float, cap: int
) -> tuple[list[CaseRun], None]:
    """Load case j at d run here, as a task's runs."""
    return [local(j, d, cap)], None


def _one_request(
    local: Callable[[Request], Outcome], request: Request
) -> tuple[list[CaseRun], Verdict | None]:
    """One d's request run here, as a task's runs and verdict."""
    return local(request)


def _one_named_later(
    local: Callable[[Request, Resolve], Outcome], resolve: Resolve, request: Request
) -> tuple[list[CaseRun], Verdict | None]:
    """One d's request whose caps are named later run here (``resolve``: where from)."""
    return local(request, resolve)


def damping_case(calibration_id: str, task: str) -> dict[str, Any]:
    """RQ job: run one task of a calibration's damping stage (a load case at one d, or one
    d's request), unless it has run, is held by another, or the calibration has ended."""
    job: Job | None = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    redis = job.connection
    record = records.get_calibration(redis, calibration_id)
    spec = scratch.get_case_task(redis, calibration_id, task)
    if record is None or record.status.terminal or spec is None:
        return {"skipped": True}
    worker = job.worker_name or "?"
    holder = f"{worker}:{os.getpid()}"
    if not scratch.claim_case(redis, calibration_id, task, holder):
        return {"skipped": True}
    if "validation" in spec:
        asked = spec["validation"]

        def solve() -> Validation:
            problem = problem_of(redis, record.spec)
            memory.check(problem.n_nodes)
            reference = reference_of(redis, record.fem_hash)
            if reference is None:
                raise LookupError("the FEM reference is gone")
            return validate(problem, reference, asked["theta"], asked["depth"])

        run_task(redis, calibration_id, task, spec, holder, worker, solve,
                 stored=validation_stored)  # fmt: skip
        return {"task": task, "name": task_name(spec)}

    def run() -> tuple[list[CaseRun], Verdict | None]:
        problem = problem_of(redis, record.spec)
        memory.check(problem.n_nodes)
        stiffness = model_stiffness(problem, spec["theta"])
        targets = targets_of(redis, calibration_id, spec)
        settle, distance = spec.get("settle"), spec.get("distance")
        if "request" in spec:
            return run_request(
                problem, stiffness, spec["depth"], spec["dt"], request_of(spec),
                partial(_named, redis, calibration_id, task), settle, targets, distance,
            )  # fmt: skip
        j = spec["load_case"]
        one = run_case(
            FpmModel(problem), stiffness, spec["depth"], spec["dt"], j, spec["d"], spec["cap"],
            None if settle is None else settle[j], None if targets is None else targets[j],
            None if distance is None else distance[j],
        )  # fmt: skip
        return [one], None

    run_task(redis, calibration_id, task, spec, holder, worker, run)
    return {"task": task, "name": task_name(spec)}


def _named(redis: Redis, calibration_id: str, task: str) -> dict[str, Any] | None:
    """What a request task learns later (:func:`store.scratch.named_later`), on another
    worker: raises once the calibration has ended (its damping job will name nothing)."""
    record = records.get_calibration(redis, calibration_id)
    if record is None or record.status.terminal:
        raise RuntimeError(f"calibration {calibration_id} has ended")
    return scratch.named_later(redis, calibration_id, task)
