"""Which workers are alive, by their heartbeats.

RQ's worker registry keeps a worker that was killed (SIGKILL, lost machine) until a live
worker's maintenance cleans it up, which never happens when no worker is left: counting the
registry reports dead workers as alive. A live worker writes ``last_heartbeat`` well within
:data:`WORKER_TTL` seconds (a busy one every third of it, an idle one each time its blocking
dequeue times out, every half of it: :mod:`store.timing`), so a worker silent for longer is
dead (or hung).
"""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from rq import Queue, worker_registration
from rq.utils import as_text, now, utcparse
from rq.worker import BaseWorker

from .timing import WORKER_TTL

__all__ = ["WORKER_TTL", "alive", "count_alive", "workers"]


def workers(queue: Queue, window: float = WORKER_TTL) -> tuple[int, int]:
    """(alive, silent): the workers registered on ``queue`` whose last heartbeat is at most
    ``window`` seconds old, and those whose is older (or missing), in two round trips.

    A registered key whose hash has expired is no worker (as RQ's ``Worker.all``, which also
    drops it from the registry: that write is left to RQ)."""
    redis = queue.connection
    pipe = redis.pipeline(transaction=False)
    for key in worker_registration.get_keys(queue):
        pipe.exists(key)
        pipe.hget(key, "last_heartbeat")
    replies = pipe.execute()
    return count_alive(replies[::2], replies[1::2], window)


def count_alive(exists: list[Any], beats: list[Any], window: float = WORKER_TTL) -> tuple[int, int]:
    """(alive, silent) from each registered worker key's EXISTS and its ``last_heartbeat``."""
    cutoff = now() - timedelta(seconds=window)
    kept = [b for e, b in zip(exists, beats, strict=True) if e]
    found = sum(b is not None and utcparse(as_text(b)) >= cutoff for b in kept)
    return found, len(kept) - found


def alive(worker: BaseWorker, window: float = WORKER_TTL) -> bool:
    """True if ``worker``'s last heartbeat is at most ``window`` seconds old."""
    beat = worker.last_heartbeat  # UTC-aware
    return beat is not None and (now() - beat).total_seconds() <= window
