"""How often workers beat, and so how soon a dead worker's job is re-queued.

Everything derives from one number, the worker TTL :data:`WORKER_TTL` (``$FPM_WORKER_TTL``,
default 30 s; RQ's default is 420 s):

- an idle worker blocks in its dequeue for :func:`dequeue_timeout` (TTL / 2) and then beats
  and, every :func:`maintenance_interval`, runs RQ's maintenance, whose cleanup of the started
  registries re-queues the jobs whose worker stopped beating (they have retries);
- a busy worker beats every :func:`job_monitoring_interval` (TTL / 3), each beat pushing its
  job's expiry in the started registry to the next beat plus :func:`execution_grace` (TTL / 2;
  RQ's own grace is a fixed 60 s, too long for a minute's re-queue);
- the health check (:mod:`store.liveness`) counts a worker alive if it beat within the TTL:
  twice an idle worker's period, three times a busy one's.

So a job whose worker died is re-queued at most :func:`requeue_bound` seconds later (40 s at
the default). The API and the workers must read the same ``FPM_WORKER_TTL``.
"""

from __future__ import annotations

import os

MIN_TTL = 4
"""The shortest TTL that leaves every interval at least a second."""


def _ttl_from_environment() -> int:
    raw = os.environ.get("FPM_WORKER_TTL", "30")
    try:
        ttl = int(raw)
    except ValueError:
        raise ValueError(f"FPM_WORKER_TTL must be a whole number of seconds, not {raw!r}") from None
    if ttl < MIN_TTL:
        raise ValueError(f"FPM_WORKER_TTL must be at least {MIN_TTL} s, not {ttl}")
    return ttl


WORKER_TTL = _ttl_from_environment()
"""Seconds a worker may go without a heartbeat before it counts as dead."""


def dequeue_timeout(ttl: int = WORKER_TTL) -> int:
    """Seconds an idle worker blocks waiting for a job between heartbeats (and maintenance)."""
    return max(1, ttl // 2)


def maintenance_interval(ttl: int = WORKER_TTL) -> int:
    """Seconds between RQ maintenance runs; a second under the dequeue timeout, so an idle
    worker runs it after every dequeue timeout."""
    return max(1, dequeue_timeout(ttl) - 1)


def job_monitoring_interval(ttl: int = WORKER_TTL) -> int:
    """Seconds between the heartbeats of a busy worker (RQ's default: 30)."""
    return max(1, ttl // 3)


def execution_grace(ttl: int = WORKER_TTL) -> int:
    """Seconds a running job's entry in the started registry outlives its next expected beat."""
    return max(1, ttl // 2)


def requeue_bound(ttl: int = WORKER_TTL) -> int:
    """Seconds after which, at the latest, an idle worker re-queues the job of a worker that
    died: the dead worker's last beat plus its job's expiry, plus one dequeue timeout for an
    idle worker's maintenance to come round."""
    return job_monitoring_interval(ttl) + execution_grace(ttl) + dequeue_timeout(ttl)
