"""The workers' Redis client, which rides out a Redis outage.

Every command of a worker and of its work horses (heartbeats, dequeues, RQ's bookkeeping, a
job's progress, checkpoints and results) is retried on a connection error or a timeout, with
exponential backoff from :data:`BACKOFF_BASE` up to :data:`BACKOFF_CAP` seconds, for as long as
Redis is away: a running job pauses at its next Redis command and goes on once Redis is back
(within :data:`BACKOFF_CAP` seconds), instead of its worker quitting. Once the worker was asked
to stop (:func:`give_up`) a command fails at once, so a worker stopped during an outage exits.

The outage is logged when it starts, every :data:`LOG_EVERY` failed attempts, and when Redis
answers again; :func:`seconds_since_outage` tells the worker when it last ended.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from redis import Redis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

BACKOFF_BASE = 0.05
BACKOFF_CAP = 1.0
"""Seconds between two attempts at most: Redis back is noticed within this."""
LOG_EVERY = 30
"""Failed attempts of one command between two log lines (about half a minute)."""

log = logging.getLogger("store.connection")
T = TypeVar("T")

_giving_up = False
_outage_ended: float | None = None  # time.monotonic() of the last recovery
_nesting = threading.local()  # a command's retry may hold its connect's: only the outer logs


def give_up() -> None:
    """From now on, fail a command at once when Redis is unreachable (the worker is stopping)."""
    global _giving_up
    _giving_up = True


def seconds_since_outage() -> float | None:
    """Seconds since a command of this process last got through after failing, or None."""
    return None if _outage_ended is None else time.monotonic() - _outage_ended


class OutageRetry(Retry):
    """redis-py's Retry, for ever (until :func:`give_up`), logging the outage."""

    def __init__(self) -> None:
        super().__init__(ExponentialBackoff(cap=BACKOFF_CAP, base=BACKOFF_BASE), retries=-1)

    def call_with_retry(
        self,
        do: Callable[[], T],
        fail: Callable[..., Any],
        is_retryable: Callable[[Exception], bool] | None = None,
        with_failure_count: bool = False,
    ) -> T:
        failed = 0
        started = time.monotonic()
        depth = getattr(_nesting, "depth", 0)
        outer = depth == 0

        def on_failure(error: Exception, count: int) -> None:
            nonlocal failed
            failed = count
            if _giving_up:
                raise error
            if outer and (count == 1 or count % LOG_EVERY == 0):
                log.warning("Redis unreachable (%s); retrying every %.0f s", error, BACKOFF_CAP)
            if with_failure_count:
                fail(error, count)
            else:
                fail(error)

        _nesting.depth = depth + 1
        try:
            result = super().call_with_retry(do, on_failure, is_retryable, with_failure_count=True)
        finally:
            _nesting.depth = depth
        if failed:
            global _outage_ended
            _outage_ended = time.monotonic()
            if outer:
                log.warning("Redis is back after %.1f s", _outage_ended - started)
        return result


def connect(url: str) -> Redis:
    """A client of ``url`` whose commands wait out a Redis outage."""
    return Redis.from_url(url, health_check_interval=30, retry=OutageRetry())
