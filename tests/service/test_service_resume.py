"""A calibration whose damping stage failed leaves its FEM reference and its chains stored
(worker/jobs/: the reference by its FEM hash, the chains by the identity of their fit,
store.hashing.stiffness_hash), and a calibration of the same fit submitted after it (the spec
with another damping setting, or the same spec again) resumes from them: no FEM job, no
annealing."""

from __future__ import annotations

from typing import Any

import pytest

import worker.jobs.chains as chain_jobs
from store import keys, records, scratch
from store.hashing import stiffness_hash

pytestmark = pytest.mark.redis


def test_a_failed_damping_stage_keeps_the_reference_and_the_chains_for_a_retry(
    api, redis, run_workers, small_spec, monkeypatch: pytest.MonkeyPatch
):
    hopeless = {**small_spec, "fpm": {**small_spec["fpm"], "max_steps": 5}}
    failed = api.post("/v1/calibrations", json=hopeless).json()
    run_workers()
    done = api.get(f"/v1/calibrations/{failed['id']}").json()
    assert done["status"] == "failed" and "damping stage failed" in done["error"]
    record = records.get_calibration(redis, failed["id"])
    assert record is not None
    assert redis.exists(keys.fem_reference(record.fem_hash))
    fitted = stiffness_hash(record.spec)
    kept = [scratch.get_fitted_chain(redis, fitted, c) for c in range(record.chains)]
    assert all(k is not None for k in kept)

    def no_annealing(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the chains should have been reused")

    monkeypatch.setattr(chain_jobs, "run_chain", no_annealing)
    retry = api.post("/v1/calibrations", json=small_spec).json()  # max_steps as the example's
    assert retry["id"] != failed["id"] and retry["fem_cached"] is True
    run_workers()
    done = api.get(f"/v1/calibrations/{retry['id']}").json()
    assert done["status"] == "succeeded", done.get("error")
    assert done["progress"]["iterations"] == done["progress"]["total_iterations"] > 0
    best = min(kept, key=lambda c: c["cost"])
    # the reused chains are stage 1: the polish starts from their best state
    assert done["result"]["chains"][0]["x"] == kept[0]["x"]
    assert min(c["cost"] for c in done["result"]["chains"]) == best["cost"]


def test_a_search_too_slow_with_the_product_s_own_cap_keeps_the_static_fit(
    api, run_workers, small_spec, monkeypatch: pytest.MonkeyPatch
):
    """Through the workers: the damping job's search settles nothing with dt and max_steps
    'auto' (the product's own choice): the calibration succeeds with the static fit, its
    parameter set stored, a warning saying d is an estimate, the result unsettled."""
    from fpm.fitting.damping import stage
    from fpm.fitting.damping.unsettled import Hopeless

    def too_slow(*args: Any, **kwargs: Any) -> None:
        raise Hopeless("load case 'pull' does not settle: its decay predicts 4,000,000 steps")

    monkeypatch.setattr(stage, "fit_damping", too_slow)
    spec = {**small_spec, "fpm": {**small_spec["fpm"], "dt": "auto", "max_steps": "auto"}}
    submitted = api.post("/v1/calibrations", json=spec).json()
    run_workers()
    done = api.get(f"/v1/calibrations/{submitted['id']}").json()
    assert done["status"] == "succeeded", done.get("error")
    assert done["parameter_set_id"] is not None
    result = done["result"]
    assert result["settled"] is False and result["damping_runs"] == 0
    assert any(w.startswith("damping not fitted") and "4,000,000" in w for w in result["warnings"])
