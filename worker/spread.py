"""The damping stage's load cases spread over the free workers (issue 32, item 3).

The d search's dearest runs are the predicted d's, every load case run to its end
(docs/physics.md, *d from the spectrum*); each case's run is independent of the others'
(:func:`fpm.fitting.damping.run_case`), so the damping job hands them out as tasks:

- each task (plan, d, load case, cap) is stored under its digest (:func:`task_digest`), and,
  when other workers are idle, enqueued as a :func:`damping_case` job on the priority queue;
- whoever claims a task first runs it (:func:`store.scratch.claim_case`): a case job on another
  worker, or the damping job itself on its own threads, which leaves the first tasks to the
  free workers (one each), takes the others, and after GRACE seconds any nobody claimed; a
  holder renews its claim while it runs, so a task whose holder died is claimed again once
  the claim expires (the damping job runs it; the killed job's retry finds it run);
- the run is stored once (JSON and raw float64 displacements) and the damping job reads every
  case's run back from there, in load-case order.

A run is a deterministic function of its task, so the fitted parameters are the same to the
bit whoever runs which task, with 1, 2 or 3 workers, and after a worker died.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict
from functools import partial
from typing import Any

import numpy as np
from redis import Redis
from rq import Worker, get_current_job
from rq.job import Job

from fpm.dynamics.simulation import FpmModel
from fpm.fitting.damping import CaseRun, run_case
from fpm.fitting.damping_stage import DampingPlan
from fpm.model.stiffness import model_stiffness
from store import graph, keys, records, scratch
from store.text import escape

from . import memory
from .problems import problem_of

POLL = 0.1
"""Seconds between the damping job's looks at its tasks."""
GRACE = 2.0
"""Seconds the damping job leaves the tasks it handed out to the free workers before it runs
any of them that nobody has claimed (a free worker claims one within a fraction of that)."""


def task_digest(spec: dict[str, Any]) -> str:
    """The digest of a task's spec (floats by their exact hexadecimal form)."""
    exact = {k: [v.hex() for v in x] if k == "theta" else x for k, x in spec.items()}
    exact["d"], exact["dt"] = float(spec["d"]).hex(), float(spec["dt"]).hex()
    return hashlib.sha256(json.dumps(exact, sort_keys=True).encode()).hexdigest()[:32]


def task_name(spec: dict[str, Any]) -> str:
    """A task's span name (:mod:`store.timeline`)."""
    return f"damping: d {spec['d']:.6g}, load case {spec['load_case']}"


def to_stored(run: CaseRun) -> tuple[dict[str, Any], bytes]:
    """A case's run as stored: (JSON dict, raw float64 displacements)."""
    data = {k: v for k, v in asdict(run).items() if k != "displacements"}
    data["shape"] = list(run.displacements.shape)
    return data, np.ascontiguousarray(run.displacements, dtype=np.float64).tobytes()


def from_stored(data: dict[str, Any], raw: bytes) -> CaseRun:
    """The stored run back (:func:`to_stored`)."""
    shape = tuple(data["shape"])
    return CaseRun(
        steps=int(data["steps"]),
        state=int(data["state"]),
        settle_force=float(data["settle_force"]),
        history=[(int(n), float(r)) for n, r in data["history"]],
        displacements=np.frombuffer(raw, dtype=np.float64).reshape(shape).copy(),
    )


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
    run: Callable[[], CaseRun],
) -> None:
    """Run a claimed task (``run``), store its run and its span; on an error give the claim up
    (another may take the task) and raise."""
    start, cpu = time.time(), time.thread_time()  # the thread's CPU: its run is one thread
    try:
        with Holding(redis, calibration_id, task, holder):
            result = run()
    except BaseException:
        scratch.release_claim(redis, calibration_id, task)
        raise
    scratch.save_case_run(redis, calibration_id, task, *to_stored(result))
    span = {
        "name": task_name(spec),
        "worker": worker,
        "start": start,
        "end": time.time(),
        "cpu": time.thread_time() - cpu,
        "after": ["damping"],
    }
    scratch.add_span(redis, calibration_id, span)


def free_workers(redis: Redis, me: str) -> int:
    """Workers other than ``me`` that are idle now."""
    return sum(1 for w in Worker.all(connection=redis) if w.name != me and w.state == "idle")


class CaseSpread:
    """The :data:`fpm.fitting.damping.CaseRunner` of the damping job: a d's load cases as
    tasks, handed to free workers and run here when nobody took them (the module docstring).

    Args:
        redis, calibration_id: where the tasks go.
        plan: the damping stage's :class:`DampingPlan` (the runs' stiffness, depth, dt).
        worker: this worker's name (spans, and the claims' holder with the process id).
        timeout: a case job's timeout, s.
        going_on: called while waiting; raises to stop (the calibration was canceled).

    Attributes:
        rounds: per d handed out: (Unix start, end, the tasks' span names).
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
        self.threads = os.cpu_count() or 1
        self.rounds: list[tuple[float, float, list[str]]] = []

    def __call__(
        self, d: float, caps: list[int], local: Callable[[int, float, int], CaseRun]
    ) -> list[CaseRun]:
        start = time.time()
        specs = [
            {**asdict(self.plan), "d": d, "load_case": j, "cap": int(c)} for j, c in enumerate(caps)
        ]
        tasks = [task_digest(s) for s in specs]
        for task, spec in zip(tasks, specs, strict=True):
            scratch.add_case_task(self.redis, self.calibration_id, task, spec)
        free = free_workers(self.redis, self.worker)
        if free:
            self._enqueue(tasks, specs)
        handed = set(range(min(free, len(tasks))))  # the first ones; this job takes the rest
        futures: dict[int, Future[None]] = {}
        with ThreadPoolExecutor(min(self.threads, len(tasks))) as pool:
            while True:
                for i, future in list(futures.items()):
                    if future.done():
                        future.result()  # raises its error
                        del futures[i]
                waiting = [
                    i for i, t in enumerate(tasks)
                    if not scratch.has_case_run(self.redis, self.calibration_id, t)
                ]  # fmt: skip
                if not waiting:
                    break
                if handed and time.time() > start + GRACE:
                    handed = set()  # not claimed by now: nobody took them
                for i in reversed(waiting):
                    if i in futures or i in handed or len(futures) >= self.threads:
                        continue
                    if scratch.claim_case(self.redis, self.calibration_id, tasks[i], self.holder):
                        futures[i] = pool.submit(
                            run_task, self.redis, self.calibration_id, tasks[i], specs[i],
                            self.holder, self.worker,
                            partial(local, i, d, caps[i]),
                        )  # fmt: skip
                self.going_on()
                time.sleep(POLL)
        runs = []
        for task in tasks:
            stored = scratch.get_case_run(self.redis, self.calibration_id, task)
            assert stored is not None
            runs.append(from_stored(*stored))
        self.rounds.append((start, time.time(), [task_name(s) for s in specs]))
        return runs

    def _enqueue(self, tasks: list[str], specs: list[dict[str, Any]]) -> None:
        """A case job per task not run yet, on the priority queue (no failure callback: a case
        job that fails loses nothing, the damping job runs its task)."""
        record = records.get_calibration(self.redis, self.calibration_id)
        name = escape(record.name) if record is not None else self.calibration_id
        q = graph.priority_queue(self.redis)
        for task, spec in zip(tasks, specs, strict=True):
            if scratch.has_case_run(self.redis, self.calibration_id, task):
                continue
            q.enqueue_call(
                keys.CASE_JOB,
                args=(self.calibration_id, task),
                job_id=keys.case_job_id(self.calibration_id, task),
                timeout=self.timeout,
                result_ttl=600,
                failure_ttl=24 * 3600,
                description=f"{name}: {task_name(spec)}",
            )


def damping_case(calibration_id: str, task: str) -> dict[str, Any]:
    """RQ job: run one load-case task of a calibration's damping stage, unless it has run, is
    held by another, or the calibration has ended."""
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

    def run() -> CaseRun:
        problem = problem_of(redis, record.spec)
        memory.check(problem.n_nodes)
        stiffness = model_stiffness(problem, spec["theta"])
        return run_case(
            FpmModel(problem), stiffness, spec["depth"], spec["dt"], spec["load_case"],
            spec["d"], spec["cap"],
        )  # fmt: skip

    run_task(redis, calibration_id, task, spec, holder, worker, run)
    return {"task": task, "load_case": spec["load_case"]}
