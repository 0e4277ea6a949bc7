"""Counts of the jobs in the project's queues and of the workers by state, for the health
endpoint and the metrics (reads only; no numerics)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from redis import Redis
from rq import Worker
from rq.job import Job, JobStatus
from rq.utils import as_text, current_timestamp

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


def all_job_counts(redis: Redis) -> dict[str, JobCounts]:
    """The job counts of every queue of the project, by queue name, in one round trip (two
    when some jobs failed).

    Reads only: RQ's own counts first run each registry's cleanup (the started registry's
    moves abandoned jobs to the failed one, a write and several round trips per call, on every
    health poll); here an entry whose expiry has passed is simply not counted, and the workers'
    maintenance cleans it up as before. RQ files a job stopped on request (a cancel stops its
    calibration's running jobs) in the failed registry with status ``stopped``; those are
    counted apart, so one cancel does not show as failures.
    """
    queues = graph.queues(redis)
    after = f"({current_timestamp()}"  # entries expiring later than now
    pipe = redis.pipeline(transaction=False)
    for q in queues:
        pipe.llen(q.key)
        pipe.zcard(q.deferred_job_registry.key)  # no expiry: RQ's cleanup of it does nothing
        pipe.zcount(q.started_job_registry.key, after, "+inf")
        pipe.zrangebyscore(q.failed_job_registry.key, after, "+inf")
    replies = pipe.execute()
    filed = [[as_text(j) for j in replies[4 * i + 3]] for i in range(len(queues))]
    for job_id in (j for ids in filed for j in ids):
        pipe.hget(Job.key_for(job_id), "status")
    statuses = iter(pipe.execute() if any(filed) else [])
    out = {}
    for i, q in enumerate(queues):
        stopped = sum(next(statuses) == JobStatus.STOPPED.value.encode() for _ in filed[i])
        queued, deferred, running = replies[4 * i : 4 * i + 3]
        out[q.name] = JobCounts(
            queued=queued,
            deferred=deferred,
            running=running,
            failed=len(filed[i]) - stopped,
            stopped=stopped,
        )
    return out


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
