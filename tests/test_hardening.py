"""Issue 12: ids checked before they reach a key (item 1)."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from test_service import assert_problem

from service.main import create_app
from worker import keys
from worker.hashing import spec_hash

pytestmark = pytest.mark.redis

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
