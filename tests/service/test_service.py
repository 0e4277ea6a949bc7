"""The REST API in-process (FastAPI TestClient) against a real Redis."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.main import create_app
from service.settings import Settings
from stack.redis_server import free_port
from store import keys, liveness, records
from store.status import FemStatus

pytestmark = pytest.mark.redis

PROBLEM_JSON = "application/problem+json"
EXAMPLE_A = Path(__file__).resolve().parents[2] / "examples" / "paper-material-a.json"


def assert_problem(response, status: int, field: str | None = None) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM_JSON
    body = response.json()
    assert body["status"] == status and body["title"] and body["detail"]
    assert "Traceback" not in response.text
    if field is not None:
        assert field in [e["field"] for e in body["errors"]], body
        assert field in body["detail"]
    return body


def test_submit_read_list(api, run_workers, small_spec):
    submitted = api.post("/v1/calibrations", json=small_spec)
    assert submitted.status_code == 202
    calibration = submitted.json()
    assert submitted.headers["location"] == f"/v1/calibrations/{calibration['id']}"
    assert calibration["status"] == "queued" and calibration["result"] is None
    again = api.post("/v1/calibrations", json=small_spec)
    assert again.status_code == 200 and again.json()["id"] == calibration["id"]

    assert calibration["progress"]["method"] == "two-stage"
    assert calibration["progress"]["stages"] == ["fem", "annealing", "damping", "finalize"]

    run_workers()
    done = api.get(submitted.headers["location"]).json()
    assert done["status"] == "succeeded"
    progress = done["progress"]
    assert progress["phase"] == "done" and progress["stage"] == "done"
    assert progress["iterations"] == progress["total_iterations"] > 0
    assert progress["damping"]["step"] == "damping" and progress["damping"]["runs"] > 0
    result = done["result"]
    assert result["method"] == "two-stage"
    assert set(result) >= {
        "k",
        "stiffness",
        "d",
        "d_min",
        "depth",
        "full_depth",
        "cost",
        "static_cost",
        "relative_discrepancy",
        "loaded_discrepancy",
        "discrepancy_h",
        "settle_steps",
        "seconds",
        "node_mass",
        "warnings",
        "history",
        "chains",
    }
    cases = len(small_spec["load_cases"])
    for name in ("relative_discrepancy", "loaded_discrepancy", "discrepancy_h", "settle_steps"):
        assert len(result[name]) == cases, name
    assert result["stiffness"] == {"axis": result["k"], "face": result["k"], "body": result["k"]}
    assert set(result["seconds"]) == {"stiffness", "damping", "finalize"}
    assert done["timings"]["running_seconds"] > 0

    page = api.get("/v1/calibrations", params={"status": "succeeded"}).json()
    assert [i["id"] for i in page["items"]] == [calibration["id"]] and page["total"] == 1
    assert api.get("/v1/calibrations", params={"status": "failed"}).json()["total"] == 0

    ps = api.get(f"/v1/parameter-sets/{done['parameter_set_id']}").json()
    assert (ps["k"], ps["d"], ps["depth"]) == (result["k"], result["d"], result["depth"])
    for name in ("stiffness", "d_min", "relative_discrepancy", "loaded_discrepancy", "warnings"):
        assert ps[name] == result[name], name
    assert ps["discrepancy_h"] == result["discrepancy_h"] and ps["stiffness_mode"] == "single"
    assert ps["geometry"]["nodes"] == 64 and ps["geometry"]["h"] == result["h"]
    assert ps["provenance"]["calibration_id"] == calibration["id"]
    assert ps["provenance"]["method"] == "two-stage"


def test_progress_names_each_stage(api, redis, small_spec):
    """What the status says in each phase, from the records the worker writes."""
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    key, progress_key = keys.calibration(calibration_id), keys.calibration_progress(calibration_id)

    def view(phase: str) -> dict:
        redis.hset(key, mapping={"status": "running", "phase": phase})
        return api.get(f"/v1/calibrations/{calibration_id}").json()["progress"]

    assert view("queued")["stage"] == "queued"
    chain = {"move": 7, "moves": 10, "temperature": 0.01, "best_cost": 0.3}
    redis.hset(progress_key, mapping={"0": json.dumps(chain), "1": json.dumps(chain)})
    annealing = view("annealing")
    assert annealing["stage"].startswith("stage 2 of 4: stiffness search")
    assert annealing["iterations"] == 14 and annealing["total_iterations"] == 20
    assert [c["chain"] for c in annealing["chains"]] == [0, 1]
    assert annealing["damping"] is None
    assert view("damping")["stage"] == "stage 3 of 4: damping (starting)"
    report = {"step": "damping", "runs": 3, "d": 0.2, "total_steps": None}
    redis.hset(progress_key, keys.DAMPING_PROGRESS, json.dumps({**report, "best_d": 0.1}))
    damping = view("damping")
    assert damping["stage"] == "stage 3 of 4: damping (finding the fastest-settling d)"
    assert damping["damping"]["runs"] == 3 and damping["damping"]["best_d"] == 0.1
    assert [c["chain"] for c in damping["chains"]] == [0, 1]  # the chain reports stay
    for step, doing in [
        ("polish", "polishing the stiffness"),
        ("depth", "choosing the depth"),
        ("field", "fitting the stiffness field"),
    ]:  # every phase of the stage
        redis.hset(progress_key, keys.DAMPING_PROGRESS, json.dumps({**report, "step": step}))
        assert view("damping")["stage"] == f"stage 3 of 4: damping ({doing})"
    assert view("finalize")["stage"] == "stage 4 of 4: final dynamic run and figures"

    small_spec["annealing"].update(method="paper", seed=5)
    paper = api.post("/v1/calibrations", json=small_spec).json()
    progress = paper["progress"]
    assert progress["method"] == "paper" and progress["stages"] == ["fem", "annealing", "finalize"]
    redis.hset(keys.calibration(paper["id"]), mapping={"status": "running", "phase": "annealing"})
    stage = api.get(f"/v1/calibrations/{paper['id']}").json()["progress"]["stage"]
    assert stage == "stage 2 of 3: annealing (k, d) on dynamic runs"


def test_progress_shows_the_fem_reference_s_level_while_it_runs(api, redis, small_spec):
    """The worker writes each refinement level into the reference's meta as it starts
    (worker.jobs.fem_reference); the calibration waiting on it shows the level."""
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    fem_hash = records.get_calibration(redis, calibration_id).fem_hash
    records.update_fem_meta(redis, fem_hash, {"status": FemStatus.RUNNING})
    progress = api.get(f"/v1/calibrations/{calibration_id}").json()["progress"]
    assert progress["phase"] == "fem" and progress["stage"] == "stage 1 of 4: FEM reference"
    assert progress["stage_number"] == 1
    assert progress["fem"] == {"level": None, "fem_nodes": None, "last_change": None}
    listed = api.get("/v1/calibrations").json()["items"]  # running in the listing too
    assert [(i["id"], i["status"]) for i in listed] == [(calibration_id, "running")]
    level = {"level": 2, "fem_nodes": 342225, "last_change": 3.5}
    records.update_fem_meta(redis, fem_hash, level)
    progress = api.get(f"/v1/calibrations/{calibration_id}").json()["progress"]
    assert progress["fem"] == level
    assert progress["stage"] == (
        "stage 1 of 4: FEM reference (refinement level 2: 342,225 FEM nodes)"
    )
    records.update_fem_meta(redis, fem_hash, {"status": FemStatus.SUCCEEDED})
    assert api.get(f"/v1/calibrations/{calibration_id}").json()["progress"]["fem"] is None
    assert api.get("/v1/calibrations").json()["items"][0]["status"] == "queued"


def test_a_reused_reference_keeps_the_stage_numbers(api, redis, run_workers, small_spec):
    """The second calibration on a stored FEM reference: its stiffness search is stage 2 of 4
    as the first's was (it was 1 of 3), and the status names the spec's load cases."""
    small_spec["load_cases"][0]["name"] = "press on top"
    first = api.post("/v1/calibrations", json=small_spec).json()
    run_workers()
    small_spec["annealing"]["seed"] = 99
    second = api.post("/v1/calibrations", json=small_spec).json()
    assert second["fem_cached"] is True
    assert second["progress"]["stages"] == first["progress"]["stages"]
    assert second["progress"]["stage"] == "queued (FEM reference reused)"
    redis.hset(keys.calibration(second["id"]), mapping={"status": "running", "phase": "annealing"})
    progress = api.get(f"/v1/calibrations/{second['id']}").json()["progress"]
    assert progress["stage"].startswith("stage 2 of 4: stiffness search")
    assert progress["stage_number"] == 2
    names = [c.get("name") for c in small_spec["load_cases"]]
    expected = [n or f"load case {i + 1}" for i, n in enumerate(names)]
    assert second["load_cases"] == expected and expected[0] == "press on top"
    done = api.get(f"/v1/calibrations/{first['id']}").json()
    assert done["load_cases"] == expected and len(done["result"]["relative_discrepancy"]) == len(
        expected
    )


def test_records_of_an_older_version_are_served_without_a_500(api, redis, run_workers, small_spec):
    """Results and parameter sets stored before the two-stage fields (e.g. in ./data)."""
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    done = api.get(f"/v1/calibrations/{calibration_id}").json()
    old_result = {k: v for k, v in done["result"].items() if k != "relative_discrepancy"}
    redis.hset(keys.calibration(calibration_id), "result", json.dumps(old_result))
    ps_id = done["parameter_set_id"]
    old_set = api.get(f"/v1/parameter-sets/{ps_id}").json()
    old_set.pop("relative_discrepancy")
    redis.set(keys.parameter_set(ps_id), json.dumps(old_set))
    view = api.get(f"/v1/calibrations/{calibration_id}").json()
    assert view["status"] == "succeeded" and view["result"] is None
    assert "older version" in view["error"]
    assert api.get("/v1/parameter-sets").json() == {"items": [], "total": 0}
    assert "older version" in assert_problem(api.get(f"/v1/parameter-sets/{ps_id}"), 410)["detail"]


def test_a_neo_hookean_parameter_set_is_served(api, run_workers, small_spec):
    """A neo-Hookean set's material names its model (a string beside the constants): reading
    or listing it answered 500 while the schema wanted every material value a float."""
    small_spec["material"]["model"] = "neo-hookean"
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    done = api.get(f"/v1/calibrations/{calibration_id}").json()
    assert done["status"] == "succeeded", done["error"]
    read = api.get(f"/v1/parameter-sets/{done['parameter_set_id']}")
    assert read.status_code == 200 and read.json()["material"]["model"] == "neo-hookean"
    listed = api.get("/v1/parameter-sets")
    assert listed.status_code == 200 and listed.json()["items"] == [read.json()]


def test_the_default_volume_model_with_validation_cases_runs_end_to_end(
    api, run_workers, small_spec
):
    """A spec that names no model gets families+volume; its validation cases are solved by the
    FEM with the load cases, reported in the result and the parameter set, and the parameter
    set exports with kappa per hexahedron."""
    del small_spec["fpm"]["stiffness"]
    del small_spec["fpm"]["dt"]
    del small_spec["fpm"]["max_steps"]
    small_spec["validation_cases"] = [
        {"name": "sideways", "forces": [{"node": 63, "vector": [0.01, 0, 0]}]}
    ]
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    done = api.get(f"/v1/calibrations/{calibration_id}").json()
    assert done["status"] == "succeeded", done["error"]
    result = done["result"]
    assert result["stiffness_mode"] == "families+volume" and result["volume_stiffness"] > 0
    assert result["validation_cases"] == ["sideways"]
    assert len(result["validation_relative_discrepancy"]) == 1
    assert 0 < result["dt"] <= 1e-3
    ps = api.get(f"/v1/parameter-sets/{done['parameter_set_id']}").json()
    assert ps["volume_stiffness"] == result["volume_stiffness"] and ps["dt"] == result["dt"]
    assert ps["validation_relative_discrepancy"] == result["validation_relative_discrepancy"]
    path = f"/v1/parameter-sets/{done['parameter_set_id']}/export"
    assert api.get(path, params={"format": "json"}).status_code == 202  # a worker makes it
    run_workers()
    exported = api.get(path, params={"format": "json"})
    assert exported.status_code == 200
    model = exported.json()
    assert model["volume_stiffness"] == [result["volume_stiffness"]] * len(model["hexahedra"])


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"validation_cases": [{"forces": []}]}, "validation_cases"),
        ({"validation_cases": [{"forces": [{"node": 10_000, "vector": [0, 0, 1]}]}]},
         "validation_cases"),
        ({"validation_cases": [{"forces": [{"at": [9, 9, 9], "vector": [0, 0, 1]}]}]},
         "validation_cases"),
    ],
)  # fmt: skip
def test_bad_validation_cases_are_422_naming_the_field(api, redis, small_spec, change, field):
    body = assert_problem(api.post("/v1/calibrations", json={**small_spec, **change}), 422)
    fields = [e["field"] for e in body["errors"]]
    assert any(f.startswith(field) for f in fields), fields
    assert not redis.keys("*")


def test_listing_is_newest_first_and_paginated(api, small_spec):
    ids = []
    for seed in range(3):
        small_spec["annealing"]["seed"] = seed
        ids.append(api.post("/v1/calibrations", json=small_spec).json()["id"])
        time.sleep(0.01)
    page = api.get("/v1/calibrations", params={"offset": 1, "limit": 1}).json()
    assert page["total"] == 3 and [i["id"] for i in page["items"]] == [ids[1]]
    assert [i["id"] for i in api.get("/v1/calibrations").json()["items"]] == ids[::-1]


def test_parameter_sets_filtered_by_material(api, run_workers, small_spec):
    api.post("/v1/calibrations", json=small_spec)
    small_spec["material"]["youngs_modulus"] = 20000.0
    small_spec["geometry"]["connectivity"] = "axis"
    small_spec.update(name="stiff axis box")
    small_spec["fpm"]["stiffness"] = "families"
    api.post("/v1/calibrations", json=small_spec)
    run_workers()
    everything = api.get("/v1/parameter-sets").json()
    assert everything["total"] == 2
    soft = api.get("/v1/parameter-sets", params={"youngs_modulus": 1e4, "poisson_ratio": 0.45})
    assert [p["material"]["youngs_modulus"] for p in soft.json()["items"]] == [1e4]
    assert api.get("/v1/parameter-sets", params={"density": 999}).json()["total"] == 0
    (axis,) = api.get("/v1/parameter-sets", params={"connectivity": "axis"}).json()["items"]
    assert axis["material"]["youngs_modulus"] == 2e4 and axis["stiffness_mode"] == "families"
    assert list(axis["stiffness"]) == ["axis"] and axis["k"] == axis["stiffness"]["axis"]
    named = api.get("/v1/parameter-sets", params={"name": "STIFF"}).json()["items"]
    assert [p["id"] for p in named] == [axis["id"]]
    assert (
        api.get("/v1/parameter-sets", params={"connectivity": "full", "name": "stiff"}).json()[
            "total"
        ]
        == 0
    )
    assert_problem(api.get("/v1/parameter-sets/ps-nothing"), 404)


def test_cancel(api, small_spec):
    calibration = api.post("/v1/calibrations", json=small_spec).json()
    canceled = api.delete(f"/v1/calibrations/{calibration['id']}")
    assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"
    assert api.delete(f"/v1/calibrations/{calibration['id']}").json()["status"] == "canceled"
    # A canceled calibration does not block a new one of the same spec.
    again = api.post("/v1/calibrations", json=small_spec)
    assert again.status_code == 202 and again.json()["id"] != calibration["id"]
    assert_problem(api.delete("/v1/calibrations/nope"), 404)


def test_cancel_of_a_finished_calibration_conflicts(api, run_workers, small_spec):
    calibration = api.post("/v1/calibrations", json=small_spec).json()
    run_workers()
    assert_problem(api.delete(f"/v1/calibrations/{calibration['id']}"), 409)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda s: s["material"].update(poisson_ratio=0.6), "material.poisson_ratio"),
        (lambda s: s["material"].pop("density"), "material.density"),
        (lambda s: s.update(colour="red"), "colour"),
        (
            lambda s: s["load_cases"][0]["forces"][0].update(at=[0.011, 0.01, 0.03]),
            "load_cases.0.forces.0.at",
        ),
        (lambda s: s["load_cases"][1].update(forces=[]), "load_cases.1.forces"),
        (lambda s: s["geometry"].update(nodes=[20, 20, 20]), "geometry"),
        (lambda s: s["annealing"].update(chains=5), "annealing.chains"),
        (lambda s: s.update(fixed=[]), "fixed"),
        (lambda s: s.update(fixed=[{"node": 0}, {"node": 1}]), "fixed"),  # a hinge: not held
        (
            lambda s: s.update(
                geometry={
                    "type": "network",
                    "nodes": [[0, 0, 0], [1, 0, 0]],
                    "springs": [[0, 1]],
                    "masses": 1.0,
                }
            ),
            "geometry.type",
        ),
    ],
)
def test_bad_spec_is_422_naming_the_field(api, redis, small_spec, change, field):
    change(small_spec)
    assert_problem(api.post("/v1/calibrations", json=small_spec), 422, field)
    assert redis.dbsize() == 0  # nothing half-written


def test_malformed_and_oversized_bodies(api, redis, settings, small_spec):
    as_json = {"content-type": "application/json"}
    body = assert_problem(api.post("/v1/calibrations", content=b"{not json", headers=as_json), 422)
    assert body["errors"]
    big = json.dumps({**small_spec, "name": "x" * settings.max_body_bytes})
    assert_problem(api.post("/v1/calibrations", content=big, headers=as_json), 413)
    assert redis.dbsize() == 0


def test_fem_reference_on_its_own(api, run_workers, small_spec):
    submitted = api.post("/v1/fem-references", json=small_spec)
    assert submitted.status_code == 202 and submitted.json()["status"] == "queued"
    assert api.post("/v1/fem-references", json=small_spec).status_code == 200
    run_workers()
    reference = api.get(submitted.headers["location"]).json()
    assert reference["status"] == "succeeded" and reference["n_nodes"] == 64
    assert len(reference["displacements"]) == 2 and len(reference["displacements"][0]) == 64
    assert len(reference["nodes"]) == 64
    assert reference["model"] == "linear" and reference["load_steps"] == []
    assert len(reference["residuals"]) == 2 and max(reference["residuals"]) < 1e-6
    # The neo-Hookean reference of the same solid reports its load steps and Newton iterations.
    hyper = {**small_spec, "material": {**small_spec["material"], "model": "neo-hookean"}}
    other = api.post("/v1/fem-references", json=hyper)
    assert other.status_code == 202 and other.headers["location"] != submitted.headers["location"]
    run_workers()
    nh = api.get(other.headers["location"], params={"arrays": False}).json()
    assert nh["status"] == "succeeded" and nh["model"] == "neo-hookean"
    assert len(nh["load_steps"]) == 2 and all(n >= 1 for n in nh["load_steps"])
    assert [len(steps) for steps in nh["newton_iterations"]] == nh["load_steps"]
    assert nh["displacements"] is None
    # A calibration of the same problem finds it stored.
    assert api.post("/v1/calibrations", json=small_spec).json()["fem_cached"] is True
    assert_problem(api.get("/v1/fem-references/abc"), 404)


def test_api_keys_protect_every_v1_route(settings, redis):
    secured = Settings(redis_url=settings.redis_url, api_keys="s3cret, other")  # as in the env
    client = TestClient(create_app(secured), raise_server_exceptions=False)
    for path in ("/v1/health", "/v1/calibrations", "/v1/parameter-sets", "/v1/fem-references/x"):
        assert_problem(client.get(path), 401)
        assert_problem(client.get(path, headers={"X-API-Key": "wrong"}), 401)
    assert client.get("/v1/health", headers={"X-API-Key": "other"}).status_code == 200
    assert client.get("/docs").status_code == 200


def test_openapi_shows_the_example_spec(api):
    schema = api.get("/openapi.json").json()
    body = schema["paths"]["/v1/calibrations"]["post"]["requestBody"]["content"]["application/json"]
    example = body["examples"]["paper-material-a"]["value"]
    assert example == json.loads(EXAMPLE_A.read_text())
    assert "Swagger" in api.get("/docs").text


def test_unknown_things_are_problems(api):
    assert_problem(api.get("/v1/calibrations/nope"), 404)
    assert_problem(api.get("/v1/nothing-here"), 404)
    assert_problem(api.put("/v1/calibrations"), 405)
    assert_problem(api.get("/v1/calibrations", params={"limit": 0}), 422, "limit")


def test_redis_unreachable_is_503_quickly(settings):
    nowhere = settings.model_copy(update={"redis_url": f"redis://127.0.0.1:{free_port()}/0"})
    client = TestClient(create_app(nowhere), raise_server_exceptions=False)
    started = time.monotonic()
    assert_problem(client.get("/v1/health"), 503)
    assert_problem(client.get("/v1/calibrations/0123456789abcdef"), 503)  # a well-formed id
    assert time.monotonic() - started < 5


def test_redis_killed_and_restarted(api, redis_server, small_spec):
    assert api.get("/v1/health").status_code == 200
    redis_server.stop(kill=True)
    try:
        assert_problem(api.post("/v1/calibrations", json=small_spec), 503)
        assert_problem(api.get("/v1/health"), 503)
    finally:
        redis_server.start()
    assert api.get("/v1/health").json()["redis"] is True
    assert api.post("/v1/calibrations", json=small_spec).status_code == 202


def test_health_counts(api, small_spec):
    api.post("/v1/calibrations", json=small_spec)
    health = api.get("/v1/health").json()
    assert health == {
        "status": "degraded",  # no worker is running
        "redis": True,
        "workers": 0,
        "silent_workers": 0,
        "heartbeat_window": liveness.WORKER_TTL,
        "queued_jobs": 1,  # the FEM job; chains and finalize wait on it
        "running_jobs": 0,
        "failed_jobs": 0,
        "keys": [{"owner": "anonymous", "active": 1, "nodes_in_flight": 64}],  # no API keys
    }
    assert keys.QUEUE == "fpm"
