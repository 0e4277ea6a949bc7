"""Per-key quotas: calibrations and lattice nodes in flight per API key (429 + Retry-After)."""

from __future__ import annotations

import copy
from typing import Any

from fastapi.testclient import TestClient
from test_service import assert_problem

from service.main import create_app
from service.settings import Settings
from store import quotas


def variant(spec: dict[str, Any], seed: int) -> dict[str, Any]:
    """A distinct calibration of the same solid (another seed: another spec hash)."""
    out = copy.deepcopy(spec)
    out["annealing"]["seed"] = seed
    return out


def client(settings: Settings, **limits: Any) -> TestClient:
    secured = Settings(
        redis_url=settings.redis_url, redis_timeout=1.0, max_nodes=2000, max_chains=4,
        api_keys="alice-key, bob-key", **limits,
    )  # fmt: skip
    return TestClient(create_app(secured), raise_server_exceptions=False)


def post(api: TestClient, key: str, spec: dict[str, Any]):
    return api.post("/v1/calibrations", json=spec, headers={"X-API-Key": key})


def test_a_key_over_its_count_gets_429_and_other_keys_do_not(settings, redis, small_spec):
    api = client(settings, max_active_per_key=2, quota_retry_after=30)
    assert post(api, "alice-key", variant(small_spec, 1)).status_code == 202
    assert post(api, "alice-key", variant(small_spec, 2)).status_code == 202
    refused = post(api, "alice-key", variant(small_spec, 3))
    body = assert_problem(refused, 429)
    assert refused.headers["Retry-After"] == "30"
    assert body["active"] == 2 and "limit 2" in body["detail"]
    assert "alice-key" not in refused.text
    # The identical spec is answered from its calibration, not counted again.
    assert post(api, "alice-key", variant(small_spec, 2)).status_code == 200
    # Another key is not affected.
    assert post(api, "bob-key", variant(small_spec, 3)).status_code == 202
    # A canceled calibration no longer counts (usage is read from the status, not a counter).
    first = api.get("/v1/calibrations", headers={"X-API-Key": "alice-key"}).json()["items"][-1]
    canceled = api.delete(f"/v1/calibrations/{first['id']}", headers={"X-API-Key": "alice-key"})
    assert canceled.status_code in (200, 202)
    assert post(api, "alice-key", variant(small_spec, 4)).status_code == 202


def test_a_key_over_its_node_budget_gets_429(settings, redis, small_spec):
    api = client(settings, max_active_per_key=0, max_nodes_per_key=100)  # small_spec: 64 nodes
    assert post(api, "alice-key", variant(small_spec, 1)).status_code == 202
    body = assert_problem(post(api, "alice-key", variant(small_spec, 2)), 429)
    assert body["nodes_in_flight"] == 64 and "limit 100" in body["detail"]
    assert post(api, "bob-key", variant(small_spec, 2)).status_code == 202


def test_usage_per_key_is_in_the_metrics_under_a_hash(settings, redis, small_spec):
    api = client(settings)
    assert post(api, "alice-key", variant(small_spec, 1)).status_code == 202
    text = api.get("/metrics").text
    owner = quotas.owner_of("alice-key")
    assert f'fpm_key_active_calibrations{{owner="{owner}"}} 1.0' in text
    assert f'fpm_key_nodes_in_flight{{owner="{owner}"}} 64.0' in text
    assert "alice-key" not in text and owner != "alice-key"


def test_health_shows_each_keys_usage_under_a_hash(settings, redis, small_spec):
    api = client(settings)
    assert post(api, "alice-key", variant(small_spec, 1)).status_code == 202
    assert post(api, "bob-key", variant(small_spec, 2)).status_code == 202
    assert post(api, "bob-key", variant(small_spec, 3)).status_code == 202
    health = api.get("/v1/health", headers={"X-API-Key": "bob-key"})
    usage = {u["owner"]: u for u in health.json()["keys"]}
    assert usage[quotas.owner_of("alice-key")]["active"] == 1
    assert usage[quotas.owner_of("bob-key")] == {
        "owner": quotas.owner_of("bob-key"),
        "active": 2,
        "nodes_in_flight": 128,
    }
    assert "alice-key" not in health.text and "bob-key" not in health.text
