"""The SDK and the fpm-client script: in-process, and over HTTP against uvicorn."""

from __future__ import annotations

import io
import json

import pytest

import fpm
from client import ApiError, Client
from client.cli import (
    discrepancy_rows,
    geometry_text,
    parameter_set_rows,
    show_calibration,
    stiffness_text,
)
from client.cli import main as cli
from client.demo import report, web_view_hint
from client.progress import ProgressBar, fraction_done, render
from fpm.fitting.calibration import calibrate
from stack.redis_server import free_port


@pytest.mark.redis
def test_sdk_calibration_equals_fpm_calibrate(sdk, run_workers, small_spec):
    submitted = sdk.calibrate(small_spec)
    assert submitted["status"] == "queued"
    run_workers()
    done = sdk.wait(submitted["id"], progress=False)
    assert done["status"] == "succeeded"
    expected = calibrate(fpm.load_problem(small_spec))
    assert done["result"]["k"] == pytest.approx(expected.parameters.k, rel=1e-12)
    assert done["result"]["stiffness"] == pytest.approx(expected.parameters.stiffness, rel=1e-12)
    assert done["result"]["d"] == pytest.approx(expected.parameters.d, rel=1e-12)
    assert done["result"]["depth"] == expected.parameters.depth
    assert done["result"]["relative_discrepancy"] == pytest.approx(
        expected.fit.relative_discrepancy, rel=1e-12
    )

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


def test_progress_bar_names_the_stage():
    progress = {"phase": "annealing", "method": "two-stage", "iterations": 5}
    calibration = {
        "name": "box",
        "status": "running",
        "progress": {**progress, "total_iterations": 10},
    }
    words = render(calibration).split()
    assert "stiffness" in words  # the two-stage method's annealing: its stiffness search
    calibration["progress"]["method"] = "paper"
    assert "annealing" in render(calibration).split()
    damping = {"step": "damping", "runs": 4, "best_d": 0.125}
    calibration["progress"].update(phase="damping", method="two-stage", damping=damping)
    line = render(calibration)
    assert "damping   d search d tried=4 fastest d=0.125" in line
    calibration["progress"]["damping"] = None  # the stage has not reported yet
    assert render(calibration).endswith("damping   starting")
    stream = io.StringIO()
    bar = ProgressBar(stream)
    for step in ("polish", "depth", "field", "damping", "damping"):
        calibration["progress"]["damping"] = {"step": step, "runs": 0}
        bar.update(calibration)
    assert len(stream.getvalue().splitlines()) == 4  # one line per step of the damping stage


def test_progress_bar_counts_stages_and_is_full_only_when_done():
    """The bar of an organ's calibration, whose FEM reference and damping stage take most of
    its time, is not full from the end of the annealing on: each stage is a share."""
    stages = ["fem", "annealing", "damping", "finalize"]
    progress = {"phase": "fem", "method": "two-stage", "stages": stages}
    calibration = {"name": "organ", "status": "running", "progress": progress}
    seen = [fraction_done(calibration)]
    assert "stage 1/4 fem" in render(calibration)
    progress["fem"] = {"level": 2, "fem_nodes": 342225, "last_change": 3.5}
    assert render(calibration).endswith(
        "stage 1/4 fem       level 2: 342,225 nodes, last change 3.5%"
    )
    progress["fem"] = None
    progress.update(phase="annealing", iterations=50, total_iterations=100)
    seen.append(fraction_done(calibration))
    progress["iterations"] = 100
    seen.append(fraction_done(calibration))
    progress["phase"] = "damping"
    for step in (None, "polish", "depth", "damping"):
        progress["damping"] = {"step": step, "runs": 0}
        seen.append(fraction_done(calibration))
    assert "stage 3/4 damping" in render(calibration)
    progress["phase"] = "finalize"
    seen.append(fraction_done(calibration))
    assert seen == [0, 0.375, 0.5, 0.5, 0.5, 0.5625, 0.6875, 0.75]
    assert fraction_done({**calibration, "status": "succeeded"}) == 1.0
    progress["phase"] = "queued"  # not a stage: nothing done yet
    assert fraction_done(calibration) == 0.0


RESULT = {
    "method": "two-stage",
    "k": 30.0,
    "stiffness": {"axis": 30.0, "face": 12.5, "body": 4.0},
    "d": 0.13,
    "d_min": 0.09,
    "depth": 3,
    "full_depth": 3,
    "relative_discrepancy": [20.0, 22.0],
    "loaded_discrepancy": [10.0, 12.0],
    "discrepancy_h": [0.5, 1.0],
    "settle_steps": [130, 140],
    "h": 0.01,
    "warnings": ["outside small strain"],
}


def test_reports_lead_with_the_relative_discrepancy():
    rows = discrepancy_rows(RESULT, ["0.05 N", "0.1 N"])
    assert rows == [
        ["0.05 N", 20.0, 10.0, 0.5, 130],
        ["0.1 N", 22.0, 12.0, 1.0, 140],
        ["mean", 21.0, 11.0, 0.75, None],
    ]
    assert stiffness_text(RESULT["stiffness"]) == "axis 30, face 12.5, body 4"
    assert stiffness_text({"axis": 29.0, "face": 29.0}, "single") == "29 (all springs)"
    calibration = {
        "id": "c1",
        "name": "box",
        "status": "succeeded",
        "parameter_set_id": "ps-1",
        "progress": {
            "phase": "done",
            "method": "two-stage",
            "stage": "done",
            "stages": ["fem", "annealing", "damping", "finalize"],
            "iterations": 20,
            "total_iterations": 20,
        },
        "result": RESULT,
    }
    text = show_calibration(calibration)
    header = next(line for line in text.splitlines() if line.startswith("load case"))
    assert header.index("relative %") < header.index("loaded nodes %") < header.index("% of h")
    assert "axis 30, face 12.5, body 4 N/m" in text and "smallest that settles: 0.09" in text
    assert "warning     outside small strain" in text
    parameter_set = {
        "id": "ps-1",
        "name": "box",
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.45, "density": 1040.0},
        "geometry": {"type": "voxels", "connectivity": "full", "nodes": 748, "h": 0.01},
        "stiffness_mode": "families",
        **{k: RESULT[k] for k in ("k", "stiffness", "d", "depth")},
        **{k: RESULT[k] for k in ("relative_discrepancy", "loaded_discrepancy", "discrepancy_h")},
    }
    (row,) = parameter_set_rows([parameter_set])
    assert row[4:7] == ["voxels, 748 nodes, full", 0.01, "axis 30, face 12.5, body 4"]
    box = {"type": "box", "size": [0.1, 0.1, 0.05], "connectivity": "axis", "nodes": 600}
    assert geometry_text(box) == "box 0.1x0.1x0.05 m, 600 nodes, axis"
    assert row[-3:] == [21.0, 11.0, 0.75]


def test_demo_report_compares_with_table_1():
    spec = {
        "load_cases": [{"name": f"{f} N", "forces": [{"vector": [0, 0, f]}]} for f in (1, 0.25)]
    }
    text = report({"paper-material-a": {"result": RESULT}}, {"paper-material-a": spec})
    assert "38.6" in text and "about 9" in text and "1.4" in text
    assert "no relative figure" in text and "not given" in text
    fit = text.split("fit (means over the load cases)\n")[1].splitlines()[2]
    # relative (mean), the paper's (none), % of h (mean), the paper's, at the smallest force
    assert fit.split()[1:4] == ["21", "not", "given"] and fit.split()[4] == "0.75"
    assert fit.split()[7] == "1"  # the smallest force (0.25 N) is the second load case


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
    assert "succeeded" in out and "relative %" in out and "% of h" in out
    assert cli(["--url", live_api, "--json", "params", "--E", "10000"]) == 0
    sets = json.loads(capsys.readouterr().out)
    assert done["parameter_set_id"] in [p["id"] for p in sets]
    assert cli(["--url", live_api, "params", "--E", "10000", "--nu", "0.45"]) == 0
    out = capsys.readouterr().out
    assert done["parameter_set_id"] in out and "(all springs)" in out
    assert "box 0.03x0.03x0.03 m, 64 nodes, full" in out and "h m" in out
    assert cli(["--url", live_api, "list"]) == 0
    assert "over http" in capsys.readouterr().out

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**small_spec, "load_cases": []}))
    assert cli(["--url", live_api, "submit", str(bad)]) == 1
    assert "load_cases" in capsys.readouterr().err


def test_cli_cannot_reach(capsys):
    assert cli(["--url", f"http://127.0.0.1:{free_port()}", "health"]) == 2
    assert "cannot reach" in capsys.readouterr().err


def test_demo_ends_with_the_web_view_url():
    assert web_view_hint("http://host:9000/") == "web view: http://host:9000/"
    assert web_view_hint(None).startswith("web view: http://127.0.0.1:8000/ once the stack")


@pytest.mark.redis
def test_submit_wait_exits_2_with_the_error_when_the_calibration_fails_or_is_canceled(
    live_api, small_spec, tmp_path, capsys
):
    """A script can trust the exit status: E = 5 Pa fails at the reference check (exit 2, the
    job's error on stderr); a calibration canceled while ``--wait`` polls exits 2 too."""
    import threading

    small_spec["name"] = "fails"
    small_spec["material"]["youngs_modulus"] = 5.0
    spec_file = tmp_path / "fails.json"
    spec_file.write_text(json.dumps(small_spec))
    assert cli(["--url", live_api, "submit", str(spec_file), "--wait"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert (
        err[-1].startswith("error: calibration ")
        and " failed: reference check failed: " in (err[-1])
    )

    slow = dict(small_spec, name="canceled while waited on", material=SLOW_MATERIAL)
    slow["annealing"] = {"chains": 1, "beta": 2e-3}  # 10^5 moves: still running
    spec_file.write_text(json.dumps(slow))
    with Client(live_api) as client:

        def cancel_when_submitted() -> None:
            for _ in range(200):
                items = client.calibrations(limit=5)["items"]
                mine = [i for i in items if i["name"] == slow["name"]]
                if mine:
                    client.cancel(mine[0]["id"])
                    return
                threading.Event().wait(0.05)

        canceller = threading.Thread(target=cancel_when_submitted)
        canceller.start()
        status = cli(["--url", live_api, "submit", str(spec_file), "--wait"])
        canceller.join()
    assert status == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(" canceled: no reason recorded")


SLOW_MATERIAL = {"youngs_modulus": 10_000.0, "poisson_ratio": 0.45, "density": 1040.0}
