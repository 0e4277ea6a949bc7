"""The SDK and the fpm-client script: in-process, and over HTTP against uvicorn."""

from __future__ import annotations

import io
import json

import pytest

import fpm
from client import ApiError, Client
from client.cli import main as cli
from client.progress import ProgressBar, render
from fpm.calibration import calibrate
from service.redis_server import free_port


@pytest.mark.redis
def test_sdk_calibration_equals_fpm_calibrate(sdk, run_workers, small_spec):
    submitted = sdk.calibrate(small_spec)
    assert submitted["status"] == "queued"
    run_workers()
    done = sdk.wait(submitted["id"], progress=False)
    assert done["status"] == "succeeded"
    expected = calibrate(fpm.load_problem(small_spec))
    assert done["result"]["k"] == pytest.approx(expected.k, rel=1e-12)
    assert done["result"]["d"] == pytest.approx(expected.d, rel=1e-12)
    assert done["result"]["depth"] == expected.depth

    found = sdk.parameter_sets(youngs_modulus=1e4, density=1040)
    assert [p["id"] for p in found] == [done["parameter_set_id"]]
    assert sdk.parameter_sets(youngs_modulus=5e4) == []
    assert sdk.parameter_set(done["parameter_set_id"])["k"] == done["result"]["k"]

    again = sdk.calibrate(small_spec)
    assert again["id"] == submitted["id"] and again["fem_cached"] is False
    small_spec["annealing"]["seed"] = 8
    assert sdk.calibrate(small_spec)["fem_cached"] is True
    reference = sdk.fem_reference(small_spec)
    assert reference["status"] == "succeeded" and len(reference["nodes"]) == 64


@pytest.mark.redis
def test_sdk_errors_and_cancel(sdk, small_spec):
    small_spec["material"]["poisson_ratio"] = 0.5
    with pytest.raises(ApiError) as info:
        sdk.calibrate(small_spec)
    assert info.value.status == 422
    assert info.value.errors[0]["field"] == "material.poisson_ratio"
    small_spec["material"]["poisson_ratio"] = 0.3
    queued = sdk.calibrate(small_spec)
    assert sdk.cancel(queued["id"])["status"] == "canceled"
    assert sdk.wait(queued["id"], progress=False)["status"] == "canceled"
    with pytest.raises(ApiError, match="404"):
        sdk.get("missing")


def test_progress_bar_on_a_pipe():
    stream = io.StringIO()
    bar = ProgressBar(stream)
    calibration = {
        "name": "box",
        "status": "running",
        "progress": {
            "phase": "annealing",
            "iterations": 50,
            "total_iterations": 100,
            "temperature": 0.01,
            "best_cost": 0.3,
        },
    }
    bar.update(calibration)
    bar.update(calibration)  # unchanged: no new line
    calibration["progress"]["iterations"] = 100
    bar.update({**calibration, "status": "succeeded"})
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert "50%" in lines[0] and "T=1.00e-02" in lines[0] and "best=0.3000" in lines[0]
    assert "100%" in lines[1] and "#" * 30 in lines[1]
    assert render(calibration).startswith("box")


@pytest.mark.redis
def test_sdk_and_cli_over_http(live_api, small_spec, tmp_path, capsys):
    small_spec["name"] = "over http"
    with Client(live_api) as client:
        assert client.health()["workers"] >= 1
        done = client.calibrate(small_spec, wait=True)
    assert done["status"] == "succeeded", done["error"]
    assert "succeeded" in capsys.readouterr().err  # the progress bar

    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(small_spec))
    assert cli(["--url", live_api, "submit", str(spec_file)]) == 0
    assert done["id"] in capsys.readouterr().out  # the same spec: the same calibration
    assert cli(["--url", live_api, "status", done["id"]]) == 0
    out = capsys.readouterr().out
    assert "succeeded" in out and "discrepancy % h" in out
    assert cli(["--url", live_api, "--json", "params", "--E", "10000"]) == 0
    sets = json.loads(capsys.readouterr().out)
    assert done["parameter_set_id"] in [p["id"] for p in sets]
    assert cli(["--url", live_api, "params", "--E", "10000", "--nu", "0.45"]) == 0
    assert done["parameter_set_id"] in capsys.readouterr().out
    assert cli(["--url", live_api, "list"]) == 0
    assert "over http" in capsys.readouterr().out

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**small_spec, "load_cases": []}))
    assert cli(["--url", live_api, "submit", str(bad)]) == 1
    assert "load_cases" in capsys.readouterr().err


def test_cli_cannot_reach(capsys):
    assert cli(["--url", f"http://127.0.0.1:{free_port()}", "health"]) == 2
    assert "cannot reach" in capsys.readouterr().err
