"""The damping stage's runs spread over the free workers.

The d search's dearest runs are the predicted d's, every load case run to its end
(docs/explanation/physics/damping-search.md, *Confirmation*): each case's run is independent of
the others' (:func:`fpm.fitting.damping.lockstep.run_case`). Then come the d that confirm it, where
the reduced steps cannot rule them out, and the margin's probes, each a d's lockstep runs whose
requests the search can name before it needs them
(:meth:`fpm.fitting.damping.lockstep._Runs.prefetch`). The damping job hands them out as tasks:

- each task (the plan, and one load case at d with its cap, or one d's request) is stored
  under its digest (:func:`task_digest`) and, when other workers are idle, enqueued as a
  :func:`damping_case` job on the priority queue (requests ahead only then);
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

import hashlib
import json
import os
import socket
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from functools import partial
from typing import Any

import numpy as np
from redis import Redis
from rq import Worker, get_current_job
from rq.job import Job
from rq.worker import BaseWorker

from fpm.dynamics.simulation import FpmModel
from fpm.fitting.damping.lockstep import (
    LATER,
    CaseRun,
    Outcome,
    Request,
    Resolve,
    Verdict,
    lockstep_cpu,
    named_later,
    run_case,
    run_request,
)
from fpm.fitting.damping.search import DampingPlan
from fpm.fitting.damping.validation import Validation, validate
from fpm.model.stiffness import model_stiffness
from store import graph, keys, records, scratch
from store.text import escape

from . import memory
from .problems import problem_of, reference_of

POLL = 0.1
"""Seconds between the damping job's looks at its tasks."""
GRACE = 2.0
"""Seconds the damping job leaves the tasks it handed out to the free workers before it runs
any of them that nobody has claimed (a free worker claims one within a fraction of that)."""


def task_digest(spec: dict[str, Any]) -> str:
    """The digest of a task's spec (floats by their exact hexadecimal form; ``after``, the
    span it waits for, left out)."""

    def exact(x: Any) -> Any:
        if isinstance(x, float):
            return x.hex()
        if isinstance(x, dict):
            return {k: exact(v) for k, v in x.items() if k != "after"}
        return [exact(v) for v in x] if isinstance(x, list | tuple) else x

    return hashlib.sha256(json.dumps(exact(spec), sort_keys=True).encode()).hexdigest()[:32]


VALIDATION_SPAN = "damping: validation cases"


def task_name(spec: dict[str, Any]) -> str:
    """A task's span name (:mod:`store.timeline`)."""
    if "validation" in spec:
        return VALIDATION_SPAN
    if "request" in spec:
        r = spec["request"]
        within = {None: "", LATER: " within their total"}.get(r["budget"], f" within {r['budget']}")
        within += " within the margin's caps" if r.get("caps_later") else ""
        return f"damping: d {r['d']:.6g}{within}, all load cases"
    return f"damping: d {spec['d']:.6g}, load case {spec['load_case']}"


def to_stored(runs: list[CaseRun], verdict: Verdict | None) -> tuple[dict[str, Any], bytes]:
    """A task's runs (and a request's verdict) as stored: (JSON dict, the runs' float64
    displacements one after the other)."""
    data: dict[str, Any] = {"runs": [], "verdict": None if verdict is None else asdict(verdict)}
    for run in runs:
        entry = {k: v for k, v in asdict(run).items() if k != "displacements"}
        data["runs"].append({**entry, "shape": list(run.displacements.shape)})
    raw = b"".join(np.ascontiguousarray(r.displacements, dtype=np.float64).tobytes() for r in runs)
    return data, raw


def from_stored(data: dict[str, Any], raw: bytes) -> tuple[list[CaseRun], Verdict | None]:
    """The stored runs and verdict back (:func:`to_stored`)."""
    runs, offset = [], 0
    for entry in data["runs"]:
        shape = tuple(entry["shape"])
        size = int(np.prod(shape)) * 8
        displacements = np.frombuffer(raw[offset : offset + size], dtype=np.float64)
        offset += size
        runs.append(
            CaseRun(
                steps=int(entry["steps"]),
                state=int(entry["state"]),
                settle_force=float(entry["settle_force"]),
                history=[(int(n), float(r)) for n, r in entry["history"]],
                displacements=displacements.reshape(shape).copy(),
            )
        )
    v = data["verdict"]
    verdict = None if v is None else Verdict(v["outcome"], v["total"], tuple(v["predicted"]))
    return runs, verdict


def validation_stored(found: Validation) -> tuple[dict[str, Any], bytes]:
    """A validation task's answer as stored (JSON; no arrays)."""
    return {"validation": asdict(found)}, b""


def save_targets(redis: Redis, calibration_id: str, targets: np.ndarray) -> None:
    """The static equilibria (L, N, 3) m the d search's runs settle towards, for its tasks."""
    data = np.ascontiguousarray(targets, dtype=np.float64)
    scratch.save_damping_targets(redis, calibration_id, list(data.shape), data.tobytes())


def targets_of(redis: Redis, calibration_id: str, spec: dict[str, Any]) -> np.ndarray | None:
    """A task's static equilibria (L, N, 3) m (None: its runs do not settle towards them).

    Raises:
        LookupError: the plan names them but they are gone."""
    if spec.get("distance") is None:
        return None
    found = scratch.get_damping_targets(redis, calibration_id)
    if found is None:
        raise LookupError("the damping stage's static equilibria are gone")
    shape, raw = found
    return np.frombuffer(raw, dtype=np.float64).reshape(shape).copy()


def request_of(spec: dict[str, Any]) -> Request:
    """A request task's :class:`Request` (JSON lists back to tuples)."""
    r = spec["request"]
    return Request(**{**r, "caps": tuple(r["caps"])})


class Holding:
    """Holds a task's claim while its run goes on: renewed every third of its expiry on a
    thread of its own (a holder killed with its process stops renewing)."""

    def __init__(self, redis: Redis, calibration_id: str, task: str, holder: str):
        self.args = (redis, calibration_id, task, holder)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._renew, daemon=True)

    def _renew(self) -> None:
        while not self.stop.wait(scratch.CLAIM_TTL / 3):
            scratch.renew_claim(*self.args)

    def __enter__(self) -> Holding:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()


def run_task(
    redis: Redis,
    calibration_id: str,
    task: str,
    spec: dict[str, Any],
    holder: str,
    worker: str,
    run: Callable[[], Any],
    clock: Callable[[], float] = time.process_time,
    stored: Callable[[Any], tuple[dict[str, Any], bytes]] = lambda found: to_stored(*found),
) -> float:
    """Run a claimed task (``run``: its runs and a request's verdict, or what ``stored``
    turns into its stored form), store them and its span, its CPU seconds by ``clock`` (a
    case job's horse: its process; the damping job's thread that ran it: :func:`task_clock`);
    return those CPU seconds. On an error give the claim up (another may take the task) and
    raise."""
    start, cpu = time.time(), clock()
    try:
        with Holding(redis, calibration_id, task, holder):
            found = run()
    except BaseException:
        scratch.release_claim(redis, calibration_id, task)
        raise
    scratch.save_case_run(redis, calibration_id, task, *stored(found))
    cpu = clock() - cpu
    span = {
        "name": task_name(spec),
        "worker": worker,
        "start": start,
        "end": time.time(),
        "cpu": cpu,
        "after": [spec["after"]],
        "task": task,
    }
    scratch.add_span(redis, calibration_id, span)
    return cpu


def task_clock() -> float:
    """A task run on one of the damping job's threads: that thread's CPU seconds and those
    its lockstep runs spent on the pool's threads
    (:func:`fpm.fitting.damping.lockstep.lockstep_cpu`)."""
    return time.thread_time() + lockstep_cpu()


def free_workers(redis: Redis, me: str, calibration_id: str) -> int:
    """Workers other than ``me`` that are idle now, or about to be: their job is one of this
    calibration's tasks, whose runs the damping job is done waiting for (RQ marks a worker
    idle a moment after its job has stored its runs)."""
    prefix = keys.case_job_id(calibration_id, "")
    return sum(
        1 for w in Worker.all(connection=redis)
        if w.name != me
        and (w.get_state() == "idle" or (w.get_current_job_id() or "").startswith(prefix))
    )  # fmt: skip


def here(workers: Sequence[BaseWorker], me: str, host: str | None, state: str) -> int:
    """Of ``workers``, those other than ``me`` on the host ``host`` in ``state`` ("busy":
    running a job, "idle")."""
    return sum(1 for w in workers if w.name != me and w.hostname == host and w.get_state() == state)


def local_threads(redis: Redis, me: str, cores: int, queued: int = 0) -> int:
    """How many tasks the damping job runs at once on its own threads: this host's ``cores``
    less the other workers here that are busy, and the idle ones that will take one of the
    ``queued`` tasks (enqueued as jobs, not claimed yet), at least one. Two tasks sharing the
    core another worker leaves would each take twice as long (the kernel shares the cores
    between worker processes evenly, not between threads), so the d whose runs they are would
    be known later and every span on the critical path would stretch; in turn they end as
    soon as the work allows. Workers on other hosts (or in containers of their own) are not
    counted."""
    workers, host = Worker.all(connection=redis), socket.gethostname()
    taking = min(here(workers, me, host, "idle"), queued)
    return max(1, cores - here(workers, me, host, "busy") - taking)


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
        request ``beside`` as a task after them, only when other workers are free: what they
        learn later (their budget or caps) is named in their tasks once the cases' runs are
        all stored."""
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
            """Once the cases' runs are all stored, what the requests learn from them (their
            budget or caps) in their tasks."""
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
        """Where request task ``task`` run here learns its budget named later."""
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
    """One d's request whose budget is named later run here (``resolve``: where from)."""
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
