"""Worker entry point: ``python -m worker [--url URL] [--burst] [QUEUE ...]``.

Run as many as you like, on as many machines as you like, against one Redis. Each worker
forks a work horse per job (so a stop request or a crash kills the horse, not the worker)
and runs RQ's maintenance every MAINTENANCE_INTERVAL seconds: a job whose worker died is
then re-queued (it has retries) and resumes from its last checkpoint.
"""

from __future__ import annotations

import argparse
import logging
import os

from redis import Redis
from rq import SimpleWorker, Worker
from rq.serializers import JSONSerializer

# jobs is imported before forking, so every work horse inherits fpm, NumPy and SciPy loaded.
from . import jobs, keys  # noqa: F401

MAINTENANCE_INTERVAL = 60
"""Seconds between RQ maintenance runs (which retry the jobs of dead workers)."""


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
    parser.add_argument("queues", nargs="*", default=[keys.QUEUE], help="queues to listen on")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    redis = Redis.from_url(args.url, health_check_interval=30)
    worker_class = SimpleWorker if args.simple else Worker
    worker = worker_class(
        args.queues,
        connection=redis,
        serializer=JSONSerializer,
        name=args.name,
        maintenance_interval=MAINTENANCE_INTERVAL,
    )
    worker.work(burst=args.burst, with_scheduler=False)


if __name__ == "__main__":
    main()
