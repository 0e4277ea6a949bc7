"""Polling stays cheap and says the same: a succeeded calibration's answer kept as its JSON bytes
(service.finished), and the health route's counts read in a few pipelined reads that never
write (store.queue_stats, store.liveness). The timings are measured by bench/bench_polling.py;
these tests check that the fast paths answer exactly what the slow ones did."""

from __future__ import annotations

import asyncio
import time

import pytest
from fastapi.routing import APIRoute, serialize_response
from fastapi.testclient import TestClient
from rq import Worker
from rq.job import Job, JobStatus
from rq.registry import StartedJobRegistry
from rq.serializers import JSONSerializer

from service.main import create_app
from service.routers import calibrations
from stack.redis_server import free_port
from store import graph, keys, liveness, queue_stats, quotas, records

pytestmark = pytest.mark.redis


def fastapi_body(api: TestClient, calibration_id: str, redis) -> bytes:
    """The body FastAPI itself makes of the route's response model for this calibration."""
    (route,) = [
        r
        for r in calibrations.router.routes
        if isinstance(r, APIRoute) and r.path == "/v1/calibrations/{calibration_id}"
        if "GET" in r.methods
    ]
    content = calibrations.read(calibration_id, redis)
    return asyncio.run(
        serialize_response(field=route.response_field, response_content=content, dump_json=True)
    )


def test_a_finished_answer_is_served_from_its_bytes_and_is_the_same(
    api, redis, run_workers, small_spec, monkeypatch
):
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    running = api.get(f"/v1/calibrations/{calibration_id}")
    assert running.json()["status"] == "queued"
    assert calibrations.FINISHED.get(redis, calibration_id) is None  # nothing kept before
    run_workers()
    first = api.get(f"/v1/calibrations/{calibration_id}")
    assert first.status_code == 200 and first.json()["status"] == "succeeded"
    assert first.headers["content-type"] == "application/json"
    assert first.content == fastapi_body(api, calibration_id, redis)

    def no_full_read(*args, **kwargs):
        raise AssertionError("the record was read in full")

    monkeypatch.setattr(records, "get_calibration_view", no_full_read)
    again = api.get(f"/v1/calibrations/{calibration_id}")
    assert again.status_code == 200 and again.content == first.content
    assert again.headers["content-length"] == first.headers["content-length"]


def test_a_changed_or_missing_record_is_read_afresh(api, redis, run_workers, small_spec):
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    kept = api.get(f"/v1/calibrations/{calibration_id}").json()
    redis.hset(keys.calibration(calibration_id), "parameter_set_id", "ps-0123456789abcdef")
    changed = api.get(f"/v1/calibrations/{calibration_id}").json()
    assert changed["parameter_set_id"] == "ps-0123456789abcdef" != kept["parameter_set_id"]
    redis.delete(keys.calibration(calibration_id))
    assert api.get(f"/v1/calibrations/{calibration_id}").status_code == 404


def test_a_kept_answer_is_no_answer_when_redis_is_down(
    api, redis, run_workers, small_spec, settings
):
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    assert api.get(f"/v1/calibrations/{calibration_id}").status_code == 200
    nowhere = settings.model_copy(update={"redis_url": f"redis://127.0.0.1:{free_port()}/0"})
    with TestClient(create_app(nowhere), raise_server_exceptions=False) as down:
        answer = down.get(f"/v1/calibrations/{calibration_id}")
    assert answer.status_code == 503 and "Redis" in answer.json()["detail"]


def rq_counts(redis) -> dict[str, tuple[int, int, int, int, int]]:
    """The job counts as RQ itself gives them (each registry cleaned up first)."""
    out = {}
    for q in graph.queues(redis):
        filed = q.failed_job_registry.get_job_ids()
        stopped = sum(
            Job.fetch(j, connection=redis, serializer=JSONSerializer).get_status() == "stopped"
            for j in filed
        )
        out[q.name] = (
            q.count,
            q.deferred_job_registry.count,
            q.started_job_registry.count,
            len(filed) - stopped,
            stopped,
        )
    return out


def test_health_counts_are_rqs_without_writing(api, redis, small_spec):
    """Queued, deferred, running, failed and stopped jobs counted as RQ counts them; an
    abandoned execution (its heartbeat expired) is neither counted nor moved: that is the
    workers' maintenance."""
    api.post("/v1/calibrations", json=small_spec)  # a queued FEM job, deferred chains
    q = graph.queue(redis)
    for status in (JobStatus.STOPPED, JobStatus.FAILED, JobStatus.FAILED):
        job = Job.create(keys.FEM_JOB, args=("x",), connection=redis, serializer=JSONSerializer)
        job.save()
        job.set_status(status)
        q.failed_job_registry.add(job, ttl=3600)
    running = Job.create(keys.FEM_JOB, args=("y",), connection=redis, serializer=JSONSerializer)
    running.save()
    running.set_status(JobStatus.STARTED)
    started = StartedJobRegistry(queue=q)
    redis.zadd(started.key, {f"{running.id}:live": time.time() + 600})
    expected = rq_counts(redis)
    counts = queue_stats.all_job_counts(redis)
    got = {
        name: (c.queued, c.deferred, c.running, c.failed, c.stopped) for name, c in counts.items()
    }
    assert got == expected
    assert expected[keys.QUEUE][2:] == (1, 2, 1)
    Worker([keys.QUEUE], connection=redis, name="w").register_birth()
    seen = queue_stats.snapshot(redis)  # the health route's, in two round trips
    assert seen.jobs == counts
    assert (seen.alive, seen.silent) == liveness.workers(q) == (1, 0)
    assert seen.usage == quotas.all_usage(redis) and seen.usage["anonymous"].active == 1

    redis.zadd(started.key, {f"{running.id}:gone": time.time() - 60})
    before = redis.zrange(started.key, 0, -1)
    health = api.get("/v1/health").json()
    assert (health["running_jobs"], health["failed_jobs"]) == (1, 2)
    assert redis.zrange(started.key, 0, -1) == before  # not cleaned up by a poll


def test_worker_liveness_reads_heartbeats_as_rq_does(redis):
    q = graph.queue(redis)
    alive = Worker([keys.QUEUE], connection=redis, name="alive")
    alive.register_birth()
    alive.heartbeat()
    silent = Worker([keys.QUEUE], connection=redis, name="silent")
    silent.register_birth()
    redis.hdel(silent.key, "last_heartbeat")
    gone = Worker([keys.QUEUE], connection=redis, name="gone")
    gone.register_birth()
    redis.delete(gone.key)  # expired: still in the queue's set
    expected = [liveness.alive(w) for w in Worker.all(queue=q)]
    assert liveness.workers(q) == (sum(expected), len(expected) - sum(expected)) == (1, 1)
