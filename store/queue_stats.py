"""Counts of the jobs in the project's queues and of the workers by state, for the health
endpoint and the metrics (reads only; no numerics)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from redis import Redis
from rq import Queue, Worker
from rq.job import Job, JobStatus

from . import graph, liveness

WORKER_STATES = ("busy", "idle", "suspended", "silent")
"""What :func:`worker_states` counts: 'silent' is a registered worker with no recent heartbeat
(dead or hung, :mod:`store.liveness`)."""


@dataclass(frozen=True)
class JobCounts:
    """The jobs of one queue: waiting to be picked up (``queued``), waiting on other jobs
    (``deferred``), running, failed, and stopped (by a cancel: not failures)."""

    queued: int
    deferred: int
    running: int
    failed: int
    stopped: int


def job_counts(queue: Queue) -> JobCounts:
    """Count ``queue``'s jobs.

    RQ files a job stopped on request (a cancel stops its calibration's running jobs) in the
    failed registry with status ``stopped``; those are counted apart, so one cancel does not
    show as failures.
    """
    filed = queue.failed_job_registry.get_job_ids()
    stopped = 0
    if filed:
        pipe = queue.connection.pipeline(transaction=False)
        for job_id in filed:
            pipe.hget(Job.key_for(job_id), "status")
        stopped = sum(1 for s in pipe.execute() if s == JobStatus.STOPPED.value.encode())
    return JobCounts(
        queued=queue.count,
        deferred=queue.deferred_job_registry.count,
        running=queue.started_job_registry.count,
        failed=len(filed) - stopped,
        stopped=stopped,
    )


def all_job_counts(redis: Redis) -> dict[str, JobCounts]:
    """:func:`job_counts` of every queue of the project, by queue name."""
    return {q.name: job_counts(q) for q in graph.queues(redis)}


def worker_states(redis: Redis) -> dict[str, int]:
    """Workers of the project by state (:data:`WORKER_STATES`), each counted once."""
    counts: Counter[str] = Counter({state: 0 for state in WORKER_STATES})
    for worker in Worker.all(queue=graph.queue(redis)):
        if not liveness.alive(worker):
            counts["silent"] += 1
        else:
            state = worker.get_state()
            counts[state if state in ("busy", "suspended") else "idle"] += 1
    return dict(counts)
