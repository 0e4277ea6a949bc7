"""Prometheus metrics at /metrics."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from rq import Worker
from test_queues import add_failed_jobs

from service.main import create_app
from stack.redis_server import free_port
from store import keys

pytestmark = pytest.mark.redis

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def scrape(client: TestClient) -> Samples:
    """Every sample of /metrics by (name, labels)."""
    answer = client.get("/metrics")
    assert answer.status_code == 200
    assert answer.headers["content-type"].startswith("text/plain")
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(answer.text)
        for s in family.samples
    }


def value(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, frozenset(labels.items()))]


def test_requests_per_route_and_queues_workers_calibrations(api, redis, run_workers, small_spec):
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    for _ in range(3):
        assert api.get(f"/v1/calibrations/{calibration_id}").status_code == 200
    assert api.get("/v1/calibrations/0123456789abcdef").status_code == 404
    assert api.get("/v1/no-such-route/7").status_code == 404
    samples = scrape(api)

    one = "/v1/calibrations/{calibration_id}"  # the route's template: no series per id
    assert value(samples, "http_requests_total", handler=one, method="GET", status="200") == 3
    assert value(samples, "http_requests_total", handler=one, method="GET", status="404") == 1
    post = {"handler": "/v1/calibrations", "method": "POST"}
    assert value(samples, "http_requests_total", **post, status="202") == 1
    assert value(samples, "http_request_duration_seconds_count", handler=one, method="GET") == 4
    assert value(samples, "http_request_duration_seconds_sum", handler=one, method="GET") > 0
    buckets = [
        dict(labels)["le"]
        for name, labels in samples
        if name == "http_request_duration_seconds_bucket" and dict(labels)["handler"] == one
    ]
    assert "+Inf" in buckets and len(buckets) > 2
    assert value(samples, "http_requests_total", handler="none", method="GET", status="404") == 1
    handlers = {dict(labels).get("handler") for _, labels in samples}
    assert not any(calibration_id in (h or "") for h in handlers)
    assert "/metrics" not in handlers

    assert value(samples, "fpm_redis_up") == 1
    # Submitted, nothing run: the FEM job (a small problem's: on the priority queue) waits;
    # chains, damping and finalize are deferred.
    assert value(samples, "fpm_queue_depth", queue=keys.QUEUE) == 0
    assert value(samples, "fpm_queue_depth", queue=keys.PRIORITY_QUEUE) == 1
    assert value(samples, "fpm_jobs", queue=keys.QUEUE, state="deferred") == 2
    assert value(samples, "fpm_jobs", queue=keys.PRIORITY_QUEUE, state="deferred") == 2
    assert value(samples, "fpm_calibrations", status="queued") == 1
    assert value(samples, "fpm_calibrations", status="succeeded") == 0
    assert value(samples, "fpm_calibration_duration_seconds_count") == 0
    assert value(samples, "fpm_cost_evaluations_total") == 0
    assert {s: value(samples, "fpm_workers", state=s) for s in ("busy", "idle")} == {
        "busy": 0,
        "idle": 0,
    }

    idle = Worker(list(keys.QUEUES), connection=redis, name="idle-one")
    idle.register_birth()
    busy = Worker(list(keys.QUEUES), connection=redis, name="busy-one")
    busy.register_birth()
    busy.set_state("busy")
    run_workers()
    samples = scrape(api)
    assert value(samples, "fpm_workers", state="idle") == 1
    assert value(samples, "fpm_workers", state="busy") == 1
    assert value(samples, "fpm_workers", state="silent") == 0
    assert value(samples, "fpm_calibrations", status="succeeded") == 1
    assert value(samples, "fpm_calibrations", status="queued") == 0
    assert value(samples, "fpm_parameter_sets") == 1
    done = api.get(f"/v1/calibrations/{calibration_id}").json()
    took = done["timings"]["running_seconds"]
    assert value(samples, "fpm_calibration_duration_seconds_count") == 1
    assert value(samples, "fpm_calibration_duration_seconds_sum") == pytest.approx(took)
    chains = sum(c["evaluations"] for c in done["result"]["chains"])
    assert value(samples, "fpm_cost_evaluations_total") == chains > 0
    for queue in keys.QUEUES:
        assert value(samples, "fpm_queue_depth", queue=queue) == 0
        assert value(samples, "fpm_jobs", queue=queue, state="failed") == 0


def test_metrics_without_redis_still_answer(settings):
    nowhere = settings.model_copy(update={"redis_url": f"redis://127.0.0.1:{free_port()}/0"})
    client = TestClient(create_app(nowhere), raise_server_exceptions=False)
    samples = scrape(client)
    assert value(samples, "fpm_redis_up") == 0
    assert not any(name.startswith("fpm_queue") for name, _ in samples)


def test_jobs_stopped_by_a_cancel_are_counted_apart_from_failures(api, redis):
    add_failed_jobs(redis, stopped=2, failed=1)
    samples = scrape(api)
    assert value(samples, "fpm_jobs", queue=keys.QUEUE, state="failed") == 1
    assert value(samples, "fpm_jobs", queue=keys.QUEUE, state="stopped") == 2
