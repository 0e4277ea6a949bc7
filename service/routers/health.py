"""/v1/health: is Redis reachable, are workers alive, how deep is the queue."""

from __future__ import annotations

from fastapi import APIRouter
from rq import Worker

from worker import graph

from ..deps import RedisDep
from ..schemas import Health

router = APIRouter(prefix="/v1/health", tags=["health"])


@router.get("")
def health(redis: RedisDep) -> Health:
    """200 with counts when Redis answers (503 problem+json when it does not)."""
    redis.ping()
    q = graph.queue(redis)
    workers = Worker.count(queue=q)
    return Health(
        status="ok" if workers else "degraded",
        redis=True,
        workers=workers,
        queued_jobs=q.count,
        running_jobs=q.started_job_registry.count,
        failed_jobs=q.failed_job_registry.count,
    )
