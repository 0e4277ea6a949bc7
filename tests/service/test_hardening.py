"""Hardening: ids checked before they reach a key, free text without control
characters or lone surrogates, user text escaped in the worker log, health counting only
workers with a recent heartbeat."""

from __future__ import annotations

import json
import logging
import signal
import time
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient
from rq import SimpleWorker, Worker
from rq.serializers import JSONSerializer
from rq.utils import now, utcformat
from test_service import assert_problem

from fpm import ProblemSpec
from service.limits import dump_spec
from service.main import create_app
from store import graph, keys, liveness
from store.graph import JobOptions
from store.hashing import spec_hash

pytestmark = pytest.mark.redis

FORGED = "x\r\n2026-01-01 00:00:00,000 rq.worker FORGED"

# --- 1. ids in paths ---------------------------------------------------------------------------


@pytest.fixture
def calibration_id(api, redis, small_spec) -> str:
    """A queued calibration with a chain's progress and result stored beside its record."""
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    redis.hset(keys.calibration_progress(calibration_id), "0", json.dumps({"move": 3}))
    redis.set(keys.chain_result(calibration_id, 0), "{}")
    redis.set(keys.chain_checkpoint(calibration_id, 0), "{}")
    return calibration_id


@pytest.mark.parametrize("suffix", [":progress", ":chain:0", ":checkpoint:0", ":damping", "*"])
@pytest.mark.parametrize("method", ["GET", "DELETE"])
def test_an_id_naming_another_key_is_404(api, redis, calibration_id, suffix, method):
    before = {k: redis.type(k) for k in redis.keys("fpm:calibration:*")}
    assert_problem(api.request(method, f"/v1/calibrations/{calibration_id}{suffix}"), 404)
    assert {k: redis.type(k) for k in redis.keys("fpm:calibration:*")} == before
    assert api.get(f"/v1/calibrations/{calibration_id}").json()["status"] == "queued"


@pytest.mark.parametrize(
    "path",
    [
        "/v1/calibrations/{cal}:progress",
        "/v1/calibrations/{cal_upper}",
        "/v1/calibrations/{cal}0",
        "/v1/calibrations/%0d%0aFORGED",
        "/v1/fem-references/{fem}:meta",
        "/v1/fem-references/{fem_upper}",
        "/v1/fem-references/{fem_short}",
        "/v1/parameter-sets/ps-{cal}:x",
        "/v1/parameter-sets/{cal}",
        "/v1/parameter-sets/ps-{cal_upper}",
    ],
)
def test_ids_of_another_form_are_404_for_every_resource(api, calibration_id, path):
    fem = api.get(f"/v1/calibrations/{calibration_id}").json()["fem_reference_id"]
    filled = path.format(
        cal=calibration_id,
        cal_upper=calibration_id.upper(),
        fem=fem,
        fem_upper=fem.upper(),
        fem_short=fem[:40],
    )
    body = assert_problem(api.get(filled), 404)
    assert "\n" not in body["detail"] and "\r" not in body["detail"]
    assert api.get(f"/v1/fem-references/{fem}").status_code == 200  # the real one still reads


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("GET", "/v1/calibrations/0123456789abcdef"),
        ("DELETE", "/v1/calibrations/0123456789abcdef"),
        ("GET", "/v1/fem-references/" + "0" * 64),
        ("GET", "/v1/parameter-sets/ps-0123456789abcdef"),
    ],
)
def test_well_formed_unknown_ids_are_404(api, method, path):
    assert_problem(api.request(method, path), 404)


def test_ids_made_match_their_forms(redis, small_spec):
    assert keys.CALIBRATION_ID.fullmatch(keys.new_calibration_id())
    assert keys.PARAMETER_SET_ID.fullmatch(keys.parameter_set_id(spec_hash(small_spec)))


def test_an_unauthenticated_bad_id_is_401_not_404(settings, redis):
    keyed = type(settings)(**{**settings.model_dump(), "api_keys": "k3y"})
    client = TestClient(create_app(keyed), raise_server_exceptions=False)
    assert_problem(client.get("/v1/calibrations/abc:progress"), 401)


# --- 2 and 3. free text ------------------------------------------------------------------------


def post_raw(api: TestClient, path: str, spec: dict) -> object:
    """POST ``spec`` as JSON text: a lone surrogate goes as the escape "\\ud800"."""
    body = json.dumps(spec)  # ensure_ascii: "\ud800" is written as the six characters \ud800
    return api.post(path, content=body, headers={"content-type": "application/json"})


@pytest.mark.parametrize(
    "text", ["\ud800", "a\udfffb", FORGED, "\x00", "bell\x07", "\x1b[31mred", "\x85", "\u2028"]
)
@pytest.mark.parametrize(
    ("place", "field"),
    [
        (lambda s, t: s.update(name=t), "name"),
        (lambda s, t: s["load_cases"][1].update(name=t), "load_cases.1.name"),
    ],
)
@pytest.mark.parametrize("path", ["/v1/calibrations", "/v1/fem-references"])
def test_control_characters_and_lone_surrogates_are_422_naming_the_field(
    api, redis, small_spec, text, place, field, path
):
    place(small_spec, text)
    body = assert_problem(post_raw(api, path, small_spec), 422, field)
    assert not any(c in body["detail"] for c in "\r\n\x00\x07\x1b\x85\u2028")
    assert redis.dbsize() == 0  # nothing stored


@pytest.mark.parametrize(
    ("key", "field"), [("\ud800", None), ("\ud800x", None), ("bad\x1bkey", "bad\\x1bkey")]
)
def test_unknown_fields_named_with_refused_characters_are_422(api, redis, small_spec, key, field):
    small_spec[key] = 1
    body = assert_problem(post_raw(api, "/v1/calibrations", small_spec), 422, field)
    assert "\x1b" not in body["detail"]
    assert redis.dbsize() == 0


def test_printable_unicode_names_are_fine(api, small_spec):
    small_spec["name"] = 'Gewebe Ü 材料 ✓ – it\'s "soft" \\r'
    small_spec["load_cases"][0]["name"] = "0.05 N ↑"
    created = post_raw(api, "/v1/calibrations", small_spec)
    assert created.status_code == 202, created.text
    assert created.json()["name"] == small_spec["name"]


def test_user_text_reaches_the_worker_log_escaped(redis, small_spec, caplog):
    # A record stored before names were checked (the API now refuses this name).
    small_spec["name"] = FORGED + "\x00\x07\x1b[2J"
    spec = dump_spec(ProblemSpec(**small_spec))
    record, _ = graph.submit_calibration(redis, spec, JobOptions(retries=0))
    caplog.set_level(logging.INFO)
    SimpleWorker(list(keys.QUEUES), connection=redis, serializer=JSONSerializer).work(
        burst=True, logging_level="INFO"
    )
    assert graph.queue(redis).count == graph.priority_queue(redis).count == 0
    logged = [r.getMessage() for r in caplog.records]
    escaped = "x\\r\\n2026-01-01 00:00:00,000 rq.worker FORGED\\x00\\x07\\x1b[2J"
    assert any(escaped in m for m in logged)
    for message in logged:
        assert not any(c in message for c in "\r\n\x00\x07\x1b"), message
    assert any(record.id in m for m in logged)


# --- 6. health ---------------------------------------------------------------------------------


def age_heartbeat(redis, worker_key: str, seconds: float) -> None:
    """Make a worker's last heartbeat ``seconds`` old (as if that time had passed)."""
    redis.hset(worker_key, "last_heartbeat", utcformat(now() - timedelta(seconds=seconds)))


def test_health_counts_only_workers_with_a_recent_heartbeat(api, redis):
    ghost = Worker([keys.QUEUE], connection=redis, name="ghost")
    ghost.register_birth()
    age_heartbeat(redis, ghost.key, liveness.WORKER_TTL + 1)
    health = api.get("/v1/health").json()
    assert (health["status"], health["workers"], health["silent_workers"]) == ("degraded", 0, 1)
    assert health["heartbeat_window"] == liveness.WORKER_TTL
    Worker([keys.QUEUE], connection=redis, name="alive").register_birth()
    health = api.get("/v1/health").json()
    assert (health["status"], health["workers"], health["silent_workers"]) == ("ok", 1, 1)


def test_health_notices_a_killed_worker_process(api, redis, worker_processes):
    process = worker_processes.start()
    deadline = time.monotonic() + 60
    while api.get("/v1/health").json()["workers"] < 1:
        assert time.monotonic() < deadline, "the worker did not register"
        time.sleep(0.1)
    worker_processes.stop(process, signal.SIGKILL)  # no chance to unregister
    q = graph.queue(redis)
    (worker_key,) = Worker.all_keys(queue=q)
    assert Worker.count(queue=q) == 1  # RQ's registry still lists it
    age_heartbeat(redis, worker_key, liveness.WORKER_TTL + 1)  # a heartbeat window later
    health = api.get("/v1/health").json()
    assert health["status"] == "degraded"
    assert (health["workers"], health["silent_workers"]) == (0, 1)
