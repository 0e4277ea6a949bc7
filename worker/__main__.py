"""Worker entry point: ``python -m worker [--url URL] [--burst] [QUEUE ...]``.

Run as many as you like, on as many machines as you like, against one Redis. A worker listens
to :data:`store.keys.QUEUES` unless told otherwise, taking the jobs that finish a calibration
(priority queue) before FEM jobs and chains. Each worker forks a work horse per job (so a stop
request or a crash kills the horse, not the worker), beats and runs RQ's maintenance at the
intervals of :mod:`store.timing`: a job whose worker died is re-queued (it has retries) within
:func:`store.timing.requeue_bound` seconds (40 at the default TTL) and resumes from its last
checkpoint. Its Redis client (:mod:`store.connection`) waits out a Redis outage: a running
job pauses and goes on once Redis is back, and no worker quits.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import sys

from redis import Redis
from redis.exceptions import RedisError
from rq import Queue, SimpleWorker, Worker
from rq.job import Job
from rq.serializers import JSONSerializer

# jobs is imported before forking, so every work horse inherits fpm, NumPy and SciPy loaded.
from store import graph, keys, timing  # noqa: F401
from store.connection import connect, give_up, seconds_since_outage

from . import jobs  # noqa: F401

PR_SET_PDEATHSIG = 1

HORSE_PRIORITY = "idle"
"""A work horse's CPU priority unless ``FPM_WORKER_PRIORITY`` says otherwise: ``idle`` (Linux's
SCHED_IDLE: the horse gets the CPU that every other process leaves) or a niceness to add to the
worker's (``0``: the same priority). A job is all computation; on a machine it shares with the API,
the API must answer first: while a worker builds a large export, several times fewer status polls
exceed 25 ms under SCHED_IDLE than at niceness 10, and the export takes as long (``python -m bench
service``, part 3, measures it). On an idle machine a job runs as fast either way, and the horses of
several workers share the CPU evenly among themselves."""


def die_with_parent(parent: int) -> None:
    """Have the kernel SIGKILL this process when its parent dies (Linux; elsewhere a no-op).

    RQ puts each work horse in a process group of its own, so a worker killed with SIGKILL
    would otherwise leave its horse running the job on, unsupervised, beside the retry.
    """
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


log = logging.getLogger("worker")


def lower_priority() -> None:
    """Set this process's CPU priority as :data:`HORSE_PRIORITY` (or ``FPM_WORKER_PRIORITY``)
    says; a value it cannot read, or a system that refuses, leaves it as it is (a warning)."""
    setting = os.environ.get("FPM_WORKER_PRIORITY", HORSE_PRIORITY).strip()
    try:
        if setting == "idle":
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        else:
            os.nice(int(setting))
    except (ValueError, OSError, AttributeError) as e:  # AttributeError: not Linux
        log.warning("work horse left at its priority (FPM_WORKER_PRIORITY=%r): %s", setting, e)


class SweepsReadyJobs:
    """After each job, move onto their queues the jobs RQ left ready but unqueued
    (:func:`store.graph.enqueue_ready`), so that no job waits for a worker's maintenance."""

    connection: Redis

    def execute_job(self, job: Job, queue: Queue) -> None:
        try:
            super().execute_job(job, queue)  # type: ignore[misc]
        finally:
            try:
                graph.enqueue_ready(self.connection)
            except RedisError as e:  # the next job's sweep, or maintenance, does it
                log.warning("could not sweep the ready registries: %s", type(e).__name__)


class RidesOutOutages:
    """The timing of :mod:`store.timing`, and a worker's part in riding out a Redis outage.

    After an outage no job is re-queued by this worker's maintenance until a busy worker that
    rode the outage out has had time to beat again (its job's entry in the started registry
    may have expired meanwhile). A stop request ends the waiting for Redis.
    """

    @property
    def dequeue_timeout(self) -> int:
        return timing.dequeue_timeout()

    @property
    def should_run_maintenance_tasks(self) -> bool:
        since = seconds_since_outage()
        settle = timing.job_monitoring_interval() + timing.execution_grace()
        if since is not None and since < settle:
            return False
        return super().should_run_maintenance_tasks  # type: ignore[misc]

    def request_stop(self, signum: int, frame: object) -> None:
        give_up()
        super().request_stop(signum, frame)  # type: ignore[misc]


class FpmSimpleWorker(RidesOutOutages, SweepsReadyJobs, SimpleWorker):
    """RQ's in-process worker (``--simple``), sweeping after each job."""


class FpmWorker(RidesOutOutages, SweepsReadyJobs, Worker):
    """RQ's forking worker whose work horses die with it, sweeping after each job."""

    _parent_pid = 0

    def get_heartbeat_ttl(self, job: Job, working_time: float = 0.0) -> int:
        """Seconds a running job's entry in the started registry lives unless renewed: the next
        beat plus :func:`store.timing.execution_grace` (RQ's grace is 60 s)."""
        interval = self.job_monitoring_interval
        if job.timeout and job.timeout > 0:
            interval = int(max(0, min(job.timeout - working_time, interval)))
        return interval + timing.execution_grace()

    def fork_work_horse(self, job: Job, queue: Queue) -> None:
        self._parent_pid = os.getpid()
        super().fork_work_horse(job, queue)

    def setup_work_horse_signals(self) -> None:
        super().setup_work_horse_signals()
        die_with_parent(self._parent_pid)
        lower_priority()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m worker", description="RQ worker for fpm calibration jobs."
    )
    parser.add_argument(
        "--url",
        default=os.environ.get("REDIS_URL", "redis://localhost:6379/0"),
        help="Redis URL (default: $REDIS_URL or redis://localhost:6379/0)",
    )
    parser.add_argument("--burst", action="store_true", help="quit once the queues are empty")
    parser.add_argument(
        "--simple", action="store_true", help="run jobs in this process (no fork; for debugging)"
    )
    parser.add_argument("--name", default=None, help="worker name (default: RQ's)")
    parser.add_argument(
        "queues",
        nargs="*",
        default=list(keys.QUEUES),
        help=f"queues to listen on, the first drained first (default: {' '.join(keys.QUEUES)})",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    redis = connect(args.url)
    worker_class = FpmSimpleWorker if args.simple else FpmWorker
    worker = worker_class(
        args.queues,
        connection=redis,
        serializer=JSONSerializer,
        name=args.name,
        maintenance_interval=timing.maintenance_interval(),
        worker_ttl=timing.WORKER_TTL,
        job_monitoring_interval=timing.job_monitoring_interval(),
    )
    try:
        worker.work(burst=args.burst, with_scheduler=False)
    except RedisError as e:  # stopped while Redis was away: its goodbye could not be written
        log.warning("stopped without reaching Redis: %s", type(e).__name__)


if __name__ == "__main__":
    main()
