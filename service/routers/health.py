"""/v1/health: is Redis reachable, are workers alive, how deep is the queue."""

from __future__ import annotations

from fastapi import APIRouter

from store import liveness, queue_stats

from ..deps import RedisDep
from ..schemas import Health, KeyUsage

router = APIRouter(prefix="/v1/health", tags=["health"])


@router.get("", operation_id="get_health")
def health(redis: RedisDep) -> Health:
    """200 with counts when Redis answers (503 problem+json when it does not).

    Workers count as alive only with a heartbeat in the last ``heartbeat_window`` seconds:
    RQ's registry alone keeps a killed worker listed (for ever, once none is left to clean it).
    Job counts cover both queues; jobs stopped by a cancel are not counted as failed. Read in
    two pipelined round trips (:func:`store.queue_stats.snapshot`; no RQ registry cleanup per
    poll: the workers' maintenance does that), so that frequent polling stays cheap.
    """
    seen = queue_stats.snapshot(redis)
    jobs = seen.jobs.values()
    return Health(
        status="ok" if seen.alive else "degraded",
        redis=True,
        workers=seen.alive,
        silent_workers=seen.silent,
        heartbeat_window=liveness.WORKER_TTL,
        queued_jobs=sum(j.queued for j in jobs),
        running_jobs=sum(j.running for j in jobs),
        failed_jobs=sum(j.failed for j in jobs),
        keys=[
            KeyUsage(owner=owner, active=used.active, nodes_in_flight=used.nodes)
            for owner, used in seen.usage.items()
            if used.active
        ],
    )
