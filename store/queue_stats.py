"""Counts of the jobs in the project's queues and of the workers by state, for the health
endpoint and the metrics (reads only; no numerics)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from redis import Redis
from rq import Queue, Worker, worker_registration
from rq.job import Job, JobStatus
from rq.utils import as_text, current_timestamp

from . import graph, keys, liveness, quotas

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
        _count_commands(pipe, q, after)
    replies = pipe.execute()
    filed = [[as_text(j) for j in replies[4 * i + 3]] for i in range(len(queues))]
    for job_id in (j for ids in filed for j in ids):
        pipe.hget(Job.key_for(job_id), "status")
    return _counts(queues, replies, filed, iter(pipe.execute() if any(filed) else []))


def _count_commands(pipe: Any, q: Queue, after: str) -> None:
    """The four reads of :func:`all_job_counts` for queue ``q`` (``after``: "(now")."""
    pipe.llen(q.key)
    pipe.zcard(q.deferred_job_registry.key)  # no expiry: RQ's cleanup of it does nothing
    pipe.zcount(q.started_job_registry.key, after, "+inf")
    pipe.zrangebyscore(q.failed_job_registry.key, after, "+inf")


def _counts(
    queues: list[Queue], replies: list[Any], filed: list[list[str]], statuses: Iterator[Any]
) -> dict[str, JobCounts]:
    """JobCounts per queue from :func:`_count_commands`' ``replies`` (4 per queue), the failed
    registries' job ids and those jobs' statuses, in order."""
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


@dataclass(frozen=True)
class Snapshot:
    """What the health route shows: workers alive and silent (:mod:`store.liveness`), the job
    counts per queue (:func:`all_job_counts`) and each API key's usage (:mod:`store.quotas`)."""

    alive: int
    silent: int
    jobs: dict[str, JobCounts]
    usage: dict[str, quotas.Usage]


def snapshot(redis: Redis, window: float = liveness.WORKER_TTL) -> Snapshot:
    """The health route's figures in two round trips (a third when an API key has
    calibrations in its set): the same as :func:`store.liveness.workers`,
    :func:`all_job_counts` and :func:`store.quotas.all_usage`, read together."""
    queues = graph.queues(redis)
    after = f"({current_timestamp()}"
    pipe = redis.pipeline(transaction=False)
    pipe.smembers(worker_registration.WORKERS_BY_QUEUE_KEY % keys.QUEUE)
    pipe.smembers(keys.owners())
    for q in queues:
        _count_commands(pipe, q, after)
    first = pipe.execute()
    workers = sorted(as_text(k) for k in first[0])
    owners = sorted(as_text(o) for o in first[1])
    replies = first[2:]
    filed = [[as_text(j) for j in replies[4 * i + 3]] for i in range(len(queues))]
    for key in workers:
        pipe.exists(key)
        pipe.hget(key, "last_heartbeat")
    for job_id in (j for ids in filed for j in ids):
        pipe.hget(Job.key_for(job_id), "status")
    for owner in owners:
        pipe.zrange(keys.owner_calibrations(owner), 0, -1, withscores=True)
    second = pipe.execute() if workers or owners or any(filed) else []
    beats = second[: 2 * len(workers)]
    alive, silent = liveness.count_alive(beats[::2], beats[1::2], window)
    statuses = iter(second[2 * len(workers) : len(second) - len(owners)])
    jobs = _counts(queues, replies, filed, statuses)
    members = dict(zip(owners, second[len(second) - len(owners) :], strict=True))
    return Snapshot(alive, silent, jobs, quotas.usages(redis, members))


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
