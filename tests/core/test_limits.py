"""The service's size limits, applied by ``fpmcal`` too: one check (:func:`fpm.limits.check_size`)
with one message, before any work; the memory a calibration needs refused in one line."""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import pytest

from fpm.limits import MAX_NODES, LimitError, Limits, check_size, node_count
from fpm.model.spec import ProblemSpec
from fpmcal.cli import error_report, main

ROOT = Path(__file__).resolve().parents[2]
SMALL: dict[str, Any] = json.loads((ROOT / "examples" / "small-box.json").read_text())


def box(nodes: list[int]) -> dict[str, Any]:
    """small-box.json with ``nodes`` per axis (its size, forces and fixed face kept)."""
    spec = copy.deepcopy(SMALL)
    spec["geometry"]["nodes"] = nodes
    return spec


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], float]:
    """(exit status, stderr lines, seconds) of ``fpmcal argv``."""
    start = time.perf_counter()
    status = main(argv)
    return status, capsys.readouterr().err.splitlines(), time.perf_counter() - start


def test_the_check_counts_nodes_without_building_and_names_the_field():
    assert node_count(ProblemSpec.model_validate(box([3, 4, 5]))) == 60
    assert check_size(ProblemSpec.model_validate(box([3, 4, 5]))) == 60
    spec = ProblemSpec.model_validate(box([1000, 1000, 1000]))  # 10^9 nodes: never built
    with pytest.raises(LimitError) as info:
        check_size(spec)
    assert (info.value.field, info.value.message) == (
        "geometry",
        f"1000000000 nodes is over the limit of {MAX_NODES}",
    )
    few = Limits(max_load_cases=1, max_chains=1)
    two = ProblemSpec.model_validate(box([3, 3, 3]))  # two load cases, 4 chains by default
    with pytest.raises(LimitError, match="^load_cases: 2 load cases is over the limit of 1$"):
        check_size(two, few)
    with pytest.raises(LimitError, match=r"^annealing.chains: \d+ chains is over the limit of 1$"):
        check_size(two, Limits(max_chains=1))


def test_the_limits_come_from_the_environment_as_the_services_do():
    assert Limits.from_environ({}) == Limits()
    assert Limits.from_environ({"FPM_MAX_NODES": "2000"}).max_nodes == 2000
    with pytest.raises(
        LimitError, match=r"^FPM_MAX_NODES: must be a whole number >= 1 \(got 'x'\)"
    ):
        Limits.from_environ({"FPM_MAX_NODES": "x"})


def test_calibrate_of_an_over_large_spec_is_one_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    """A 5,000,000-node box: refused at once (building its lattice alone would take minutes
    and gigabytes), with the service's message at the service's field."""
    path = tmp_path / "big.json"
    path.write_text(json.dumps(box([200, 200, 125])))
    status, err, seconds = cli(["calibrate", str(path)], capsys)
    assert status == 2 and seconds < 5
    assert err == [f"{path}: geometry: 5000000 nodes is over the limit of {MAX_NODES}"]
    status, err, _ = cli(["fem", str(path)], capsys)
    assert status == 2 and len(err) == 1 and "over the limit" in err[0]


def test_spec_from_mesh_with_too_many_nodes_is_refused_before_reading_the_mesh(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    argv = ["spec", "from-mesh", str(ROOT / "examples" / "lobe.vtu"), "--fix", "face:z-"]
    argv += ["--force", "face:z+:0,0,-0.1", "--E", "5000", "--nu", "0.45"]
    status, err, seconds = cli([*argv, "--nodes", "5000000"], capsys)
    assert status == 2 and seconds < 2
    assert err == [f"error: --nodes: 5000000 nodes is over the limit of {MAX_NODES}"]


def test_spec_from_mesh_whose_spacing_makes_too_many_nodes_makes_no_spec(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    """FPM_MAX_NODES as the service's setting: a lattice over it is refused, not written."""
    monkeypatch.setenv("FPM_MAX_NODES", "50")
    out = tmp_path / "lobe.json"
    argv = ["spec", "from-mesh", str(ROOT / "examples" / "lobe.vtu"), "--fix", "face:z-"]
    argv += ["--force", "face:z+:0,0,-0.1", "--E", "5000", "--nu", "0.45", "--nodes", "200"]
    status, err, _ = cli([*argv, "-o", str(out)], capsys)
    assert status == 2 and not out.exists()
    assert len(err) == 1 and err[0].startswith("error: --nodes: ")
    assert err[0].endswith(" nodes is over the limit of 50")


@pytest.mark.redis
def test_the_cli_and_the_service_refuse_with_the_same_message(
    api: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    """The test service's limit is 2,000 nodes; fpmcal with FPM_MAX_NODES=2000 says the same."""
    spec = box([20, 20, 6])
    answer = api.post("/v1/calibrations", json=spec)
    assert answer.status_code == 422
    error = answer.json()["errors"][0]
    monkeypatch.setenv("FPM_MAX_NODES", "2000")
    path = tmp_path / "over.json"
    path.write_text(json.dumps(spec))
    status, err, _ = cli(["calibrate", str(path), "-q"], capsys)
    assert status == 2
    assert err == [f"{path}: {error['field']}: {error['message']}"]
    assert error["message"] == "2400 nodes is over the limit of 2000"


def test_a_calibration_the_memory_cannot_hold_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    """The worker's estimate (worker.memory) against FPM_WORKER_MEMORY or the machine's."""
    monkeypatch.setenv("FPM_WORKER_MEMORY", "100M")
    path = tmp_path / "small.json"
    path.write_text(json.dumps(SMALL))
    status, err, _ = cli(["calibrate", str(path), "-q"], capsys)
    assert status == 1
    assert err == [
        "error: this job needs about 0.36 GB for 64 lattice nodes and this machine may use "
        "0.10 GB (FPM_WORKER_MEMORY): use a coarser spacing"
    ]


def test_running_out_of_memory_anyway_is_named():
    lines, status = error_report(MemoryError(), "spec.json")
    assert status == 1 and len(lines) == 1
    assert lines[0].startswith("error: out of memory: the problem is too large for this machine")
