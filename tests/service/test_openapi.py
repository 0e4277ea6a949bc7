"""The OpenAPI document as client generators read it, and the names and timestamps of the REST
answers."""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.redis

PROBLEM_JSON = "application/problem+json"
PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}

OPERATIONS = {
    ("post", "/v1/calibrations"): ("submit_calibration", {400, 401, 413, 422, 429, 500, 503}),
    ("get", "/v1/calibrations"): ("list_calibrations", {401, 422, 500, 503}),
    ("get", "/v1/calibrations/{calibration_id}"): ("get_calibration", {401, 404, 422, 500, 503}),
    ("delete", "/v1/calibrations/{calibration_id}"): (
        "cancel_calibration",
        {401, 404, 409, 422, 500, 503},
    ),
    ("post", "/v1/fem-references"): ("submit_fem_reference", {400, 401, 413, 422, 500, 503}),
    ("get", "/v1/fem-references/{fem_id}"): ("get_fem_reference", {401, 404, 422, 500, 503}),
    ("post", "/v1/meshes"): ("upload_mesh", {400, 401, 413, 422, 500, 503}),
    ("get", "/v1/parameter-sets"): ("list_parameter_sets", {401, 422, 500, 503}),
    ("get", "/v1/parameter-sets/{parameter_set_id}"): (
        "get_parameter_set",
        {401, 404, 410, 422, 500, 503},
    ),
    ("get", "/v1/parameter-sets/{parameter_set_id}/export"): (
        "export_parameter_set",
        {401, 404, 410, 422, 500, 503},
    ),
    ("get", "/v1/health"): ("get_health", {401, 500, 503}),
}
"""Operation id and error statuses of each route. (A 422 on a route whose only parameter is a
string id is FastAPI's: it documents one wherever a route has parameters.)"""


def operations(document: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    return {
        (method, path): operation
        for path, methods in document["paths"].items()
        for method, operation in methods.items()
    }


def walk(node: Any, where: str = "") -> list[tuple[str, dict[str, Any]]]:
    """Every object in ``node`` with its JSON path."""
    found = []
    if isinstance(node, dict):
        found.append((where, node))
        for key, value in node.items():
            found += walk(value, f"{where}/{key}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            found += walk(value, f"{where}/{i}")
    return found


def test_every_error_response_refers_to_the_one_problem_component(api):
    document = api.get("/openapi.json").json()
    schemas = document["components"]["schemas"]
    assert set(schemas["Problem"]["properties"]) == {"type", "title", "status", "detail", "errors"}
    assert schemas["Problem"]["properties"]["errors"]["anyOf"][0]["items"] == {
        "$ref": "#/components/schemas/FieldError"
    }
    assert "HTTPValidationError" not in schemas and "ValidationError" not in schemas
    errors = 0
    for (method, path), operation in operations(document).items():
        for code, response in operation["responses"].items():
            if int(code) >= 400:
                errors += 1
                assert response["content"] == {PROBLEM_JSON: {"schema": PROBLEM_REF}}, (
                    method,
                    path,
                    code,
                )
                assert response["description"]
    assert errors >= 40
    # No inline copy of the problem schema anywhere: only the component has its members.
    inline = [
        where
        for where, node in walk(document)
        if {"title", "status", "detail"} <= set(node.get("properties", {}))
    ]
    assert inline == ["/components/schemas/Problem"]


def test_operation_ids_are_readable_and_errors_as_the_routes_answer(api):
    document = operations(api.get("/openapi.json").json())
    for key, (operation_id, statuses) in OPERATIONS.items():
        operation = document[key]
        assert operation["operationId"] == operation_id, key
        assert {int(c) for c in operation["responses"] if int(c) >= 400} == statuses, key
    ids = [operation["operationId"] for operation in document.values()]
    assert len(ids) == len(set(ids))
    for operation_id in ids:  # no FastAPI-made ids (read_v1_calibrations__calibration_id__get)
        assert re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", operation_id), operation_id
        assert not re.search(r"_v1_|__|_(get|post|delete)$", operation_id), operation_id


def test_the_export_documents_its_202_and_retry_after(api):
    document = operations(api.get("/openapi.json").json())
    responses = document[("get", "/v1/parameter-sets/{parameter_set_id}/export")]["responses"]
    pending = responses["202"]
    assert pending["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/ExportPending"
    }
    assert {"Retry-After", "Location"} <= set(pending["headers"])
    assert set(responses["200"]["content"]) == {
        "application/json",
        "application/xml",
        "text/x-python",
    }
    assert "export job failed" in responses["503"]["description"]
    assert "Retry-After" in responses["503"]["headers"]


def test_no_property_collides_with_generated_code(api):
    """openapi-python-client names its working dict ``d``: a property ``d`` read into it
    left CalibrationResult a dict. The answers name the damping ``damping`` (``last_d`` in the
    damping progress); ``d`` is still sent, for existing clients, but not documented."""
    schemas = api.get("/openapi.json").json()["components"]["schemas"]
    for name in ("CalibrationResult", "ParameterSet", "DampingProgress"):
        assert "d" not in schemas[name]["properties"], name
    assert "damping" in schemas["CalibrationResult"]["properties"]
    assert "damping" in schemas["ParameterSet"]["properties"]
    assert "last_d" in schemas["DampingProgress"]["properties"]
    assert "const" not in {k for _, node in walk(schemas) for k in node}  # enums instead
    # The request's annealing.bounds.d stays (the spec's field): there it is the last
    # property and nothing reads the working dict after it, which generated code survives.
    assert list(schemas["Bounds"]["properties"])[-1] == "d"


def test_the_answers_result_is_fpms_result_with_the_rest_name_of_d():
    """One result model: the REST answer is fpm's CalibrationResult plus ``damping`` (``d``'s
    name for generated clients), so a field added to fpm's is answered too."""
    from fpm.fitting.result import StoredResult as CalibrationResult
    from service import schemas

    assert issubclass(schemas.CalibrationResult, CalibrationResult)
    extra = set(schemas.CalibrationResult.model_fields) - set(CalibrationResult.model_fields)
    assert extra == {"damping"}


def test_answers_carry_the_new_names_the_old_ones_and_iso_timestamps(api, run_workers, small_spec):
    submitted = api.post("/v1/calibrations", json=small_spec).json()
    run_workers()
    done = api.get(f"/v1/calibrations/{submitted['id']}").json()
    result, damping = done["result"], done["progress"]["damping"]
    assert result["damping"] == result["d"] > 0
    assert damping["last_d"] == damping["d"] > 0
    (ps,) = api.get("/v1/parameter-sets").json()["items"]
    assert ps["damping"] == ps["d"] == result["damping"]
    timings = done["timings"]
    for name in ("created", "started", "finished"):
        text = timings[f"{name}_at"]
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?Z", text), text
        assert abs(datetime.fromisoformat(text).timestamp() - timings[name]) < 1e-3
    (summary,) = api.get("/v1/calibrations").json()["items"]
    assert summary["created_at"] == timings["created_at"]
    assert datetime.fromisoformat(ps["created_at"]).timestamp() == pytest.approx(ps["created"])
    queued = api.post("/v1/calibrations", json={**small_spec, "name": "other"}).json()
    assert queued["timings"]["started_at"] is None and queued["timings"]["finished_at"] is None


# --- A client generated from the document, against the live stack -------------------------------


def generator() -> Path | None:
    """The openapi-python-client command of this environment, if installed."""
    path = Path(sys.executable).parent / "openapi-python-client"
    return path if path.exists() else None


@pytest.mark.skipif(
    generator() is None,
    reason="openapi-python-client is not installed (a dev dependency: it needs Python >= 3.11)",
)
def test_generated_client_types_results_and_errors(live_api, small_spec, tmp_path):
    import httpx

    document = tmp_path / "openapi.json"
    document.write_text(httpx.get(f"{live_api}/openapi.json").text)
    package = tmp_path / "fpm_api_client"
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    generated = subprocess.run(
        [str(generator()), "generate", "--path", str(document), "--output-path", str(package)]
        + ["--meta", "none"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    output = generated.stdout + generated.stderr
    assert generated.returncode == 0, output
    assert "Warning" not in output and "duplicate" not in output, output

    sys.path.insert(0, str(tmp_path))
    try:
        client_module = importlib.import_module("fpm_api_client")
        models = importlib.import_module("fpm_api_client.models")
        submit = importlib.import_module("fpm_api_client.api.calibrations.submit_calibration")
        get = importlib.import_module("fpm_api_client.api.calibrations.get_calibration")
        listing = importlib.import_module("fpm_api_client.api.parameter_sets.list_parameter_sets")
        client = client_module.Client(base_url=live_api, raise_on_unexpected_status=True)

        small_spec["name"] = "generated client"
        small_spec["annealing"]["seed"] = 21
        spec = models.ProblemSpec.from_dict(small_spec)
        assert spec.to_dict()["fpm"]["depth"] == 3
        submitted = submit.sync(client=client, body=spec)
        assert isinstance(submitted, models.Calibration)
        deadline = time.monotonic() + 60
        while True:
            done = get.sync(submitted.id, client=client)
            if done.status.value in ("succeeded", "failed", "canceled"):
                break
            assert time.monotonic() < deadline, done.status
            time.sleep(0.2)
        assert done.status == models.CalibrationStatus.SUCCEEDED, done.error
        result = done.result
        assert isinstance(result, models.CalibrationResult)  # no longer a dict
        assert isinstance(result.damping, float) and isinstance(result.k, float)
        assert isinstance(result.stiffness, models.CalibrationResultStiffness)
        assert isinstance(result.chains[0], models.ChainSummary)
        assert len(result.relative_discrepancy) == len(small_spec["load_cases"])
        assert result.additional_properties == {"d": result.damping}  # the old name, kept
        assert isinstance(done.timings.created_at, datetime)
        assert isinstance(done.progress.damping, models.DampingProgress)

        page = listing.sync(client=client, name="generated client")
        assert isinstance(page, models.ParameterSetPage)
        (ps,) = page.items
        assert isinstance(ps, models.ParameterSet) and ps.id == done.parameter_set_id
        assert ps.damping == result.damping and ps.geometry.h == result.h
        assert isinstance(ps.geometry, models.GeometrySummary) and ps.geometry.nodes == 64

        small_spec["material"]["poisson_ratio"] = 0.6
        refused = submit.sync_detailed(client=client, body=models.ProblemSpec.from_dict(small_spec))
        problem = refused.parsed
        assert refused.status_code == 422 and isinstance(problem, models.Problem)
        assert [e.field for e in problem.errors] == ["material.poisson_ratio"]
        missing = get.sync("0123456789abcdef", client=client)
        assert isinstance(missing, models.Problem) and missing.status == 404
    finally:
        sys.path.remove(str(tmp_path))
        for name in [m for m in sys.modules if m.split(".")[0] == "fpm_api_client"]:
            del sys.modules[name]
