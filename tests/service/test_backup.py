"""Store dump and restore (fpmcal store dump / restore): the backup and migration path."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import fpm
from fpm.fem.solution import FemResult
from fpmcal.cli import main
from store import keys, records

SMALL_BOX = Path(__file__).resolve().parents[2] / "examples" / "small-box.json"


def test_a_dump_restored_into_an_empty_store_dumps_the_same_lines(
    api, run_workers, redis, redis_server, small_spec, tmp_path: Path, monkeypatch, capsys
):
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    assert api.get(f"/v1/calibrations/{calibration_id}").json()["status"] == "succeeded"
    canceled = api.post("/v1/calibrations", json={**small_spec, "name": "canceled"}).json()["id"]
    api.delete(f"/v1/calibrations/{canceled}")
    monkeypatch.setenv("FPM_REDIS_URL", redis_server.url)
    first = tmp_path / "first.jsonl"
    assert main(["store", "dump", "-o", str(first)]) == 0
    lines = first.read_text().splitlines()
    header = json.loads(lines[0])
    assert header["format"] == "fpm-store-dump" and header["version"] == 1
    kinds = [json.loads(line)["kind"] for line in lines[1:]]
    assert kinds == ["fem_reference", "calibration", "calibration", "parameter_set"]

    redis.flushdb()
    assert main(["store", "restore", str(first)]) == 0
    assert "1 fem references, 2 calibrations, 1 parameter sets" in capsys.readouterr().err
    second = tmp_path / "second.jsonl"
    assert main(["store", "dump", "-o", str(second)]) == 0
    assert second.read_text() == first.read_text()
    # Idempotent: restoring again writes nothing and changes nothing.
    assert main(["store", "restore", str(first)]) == 0
    assert "0 fem references, 0 calibrations, 0 parameter sets" in capsys.readouterr().err
    assert main(["store", "dump", "-o", str(second)]) == 0
    assert second.read_text() == first.read_text()
    # The restored store serves what it served: the calibration, its parameter set, and an
    # identical spec is answered from the calibration.
    done = api.get(f"/v1/calibrations/{calibration_id}").json()
    assert done["status"] == "succeeded"
    assert api.get(f"/v1/parameter-sets/{done['parameter_set_id']}").status_code == 200
    again = api.post("/v1/calibrations", json=small_spec)
    assert again.status_code == 200 and again.json()["id"] == calibration_id
    assert redis.exists(keys.fem_reference(json.loads(lines[1])["id"]))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"format": "fpm-store-dump", "version": 2}\n', "newer than this version reads (1)"),
        ("not json\n", "not an fpm store dump"),
        ('{"format": "other"}\n', "not an fpm store dump"),
    ],
)
def test_a_file_it_cannot_restore_is_one_clear_line(
    redis, redis_server, tmp_path: Path, monkeypatch, capsys, content, message
):
    monkeypatch.setenv("FPM_REDIS_URL", redis_server.url)
    path = tmp_path / "dump.jsonl"
    path.write_text(content)
    assert main(["store", "restore", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not redis.keys("*")


def test_a_reference_stored_as_json_by_an_older_release_still_reads(redis):
    old = fpm.solve_fem(fpm.load_problem(json.loads(SMALL_BOX.read_text()))).to_dict()
    redis.set(keys.fem_reference("older"), json.dumps(old))
    assert records.get_fem_reference(redis, "older") == old
    stored = records.get_fem_arrays(redis, "older")
    assert stored is not None
    assert FemResult.from_stored(*stored).to_dict() == old
    records.save_fem_reference(redis, "newer", *stored, {"status": "succeeded"})
    assert redis.get(keys.fem_reference("newer")).startswith(records.RAW_REFERENCE)
    assert records.get_fem_reference(redis, "newer") == old
