"""Worker entry point: ``python -m worker [--url URL] [--burst] [QUEUE ...]``.

Run as many as you like, on as many machines as you like, against one Redis. A worker listens
to :data:`worker.keys.QUEUES` unless told otherwise, taking the jobs that finish a calibration
(priority queue) before FEM jobs and chains. Each worker forks a work horse per job (so a stop
request or a crash kills the horse, not the worker) and runs RQ's maintenance every
MAINTENANCE_INTERVAL seconds: a job whose worker died is then re-queued (it has retries) and
resumes from its last checkpoint.
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
from . import graph, jobs, keys  # noqa: F401
from .liveness import WORKER_TTL

MAINTENANCE_INTERVAL = 60
"""Seconds between RQ maintenance runs (which retry the jobs of dead workers)."""

PR_SET_PDEATHSIG = 1


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


class SweepsReadyJobs:
    """After each job, move onto their queues the jobs RQ left ready but unqueued
    (:func:`worker.graph.enqueue_ready`), so that no job waits for a worker's maintenance."""

    connection: Redis

    def execute_job(self, job: Job, queue: Queue) -> None:
        try:
            super().execute_job(job, queue)  # type: ignore[misc]
        finally:
            try:
                graph.enqueue_ready(self.connection)
            except RedisError as e:  # the next job's sweep, or maintenance, does it
                log.warning("could not sweep the ready registries: %s", type(e).__name__)


class FpmSimpleWorker(SweepsReadyJobs, SimpleWorker):
    """RQ's in-process worker (``--simple``), sweeping after each job."""


class FpmWorker(SweepsReadyJobs, Worker):
    """RQ's forking worker whose work horses die with it, sweeping after each job."""

    _parent_pid = 0

    def fork_work_horse(self, job: Job, queue: Queue) -> None:
        self._parent_pid = os.getpid()
        super().fork_work_horse(job, queue)

    def setup_work_horse_signals(self) -> None:
        super().setup_work_horse_signals()
        die_with_parent(self._parent_pid)


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
    redis = Redis.from_url(args.url, health_check_interval=30)
    worker_class = FpmSimpleWorker if args.simple else FpmWorker
    worker = worker_class(
        args.queues,
        connection=redis,
        serializer=JSONSerializer,
        name=args.name,
        maintenance_interval=MAINTENANCE_INTERVAL,
        worker_ttl=WORKER_TTL,
    )
    worker.work(burst=args.burst, with_scheduler=False)


if __name__ == "__main__":
    main()
