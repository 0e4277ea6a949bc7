"""worker.memory: a job its worker cannot hold is refused before it starts, with the reason."""

import pytest

from worker import memory


def test_sizes_parse():
    assert memory.parse_bytes("3G") == 3 << 30
    assert memory.parse_bytes("512m") == 512 << 20
    assert memory.parse_bytes("1000000") == 1_000_000
    with pytest.raises(ValueError):
        memory.parse_bytes("lots")


def test_the_estimate_meets_the_measured_peaks():
    """Within 5% of the organs' measured peaks (README, Performance)."""
    assert memory.estimated_bytes(19_692) == pytest.approx(0.90e9, rel=0.05)
    assert memory.estimated_bytes(93_705) == pytest.approx(2.90e9, rel=0.05)


def test_the_limit_comes_from_the_environment_then_the_cgroup(tmp_path):
    v2, v1 = tmp_path / "memory.max", tmp_path / "limit_in_bytes"
    files = (str(v2), str(v1))
    assert memory.memory_limit({}, files) is None  # neither file
    v2.write_text("max\n")
    v1.write_text("9223372036854771712\n")  # cgroup v1's "no limit"
    assert memory.memory_limit({}, files) is None
    v1.write_text("2147483648\n")
    assert memory.memory_limit({}, files) == (2 << 30, str(v1))
    v2.write_text("1073741824\n")
    assert memory.memory_limit({}, files) == (1 << 30, str(v2))
    assert memory.memory_limit({"FPM_WORKER_MEMORY": "3G"}, files) == (3 << 30, "FPM_WORKER_MEMORY")


def test_a_job_over_the_limit_is_refused_with_the_reason():
    memory.check(93_718, (3_000_000_000, "FPM_WORKER_MEMORY"))  # fits the 3 GB goal
    with pytest.raises(memory.MemoryRefused, match=r"about 2\.90 GB for 93,718 lattice nodes"):
        memory.check(93_718, (2 << 30, "/sys/fs/cgroup/memory.max"))


def test_no_limit_no_refusal(monkeypatch):
    monkeypatch.setattr(memory, "memory_limit", lambda **_: None)
    memory.check(10**7)


def test_a_worker_too_small_fails_the_calibration_with_the_reason(
    api, run_workers, small_spec, monkeypatch
):
    """The FEM job refuses before solving; retries refuse the same way; the calibration fails
    saying how much the job needs and what the worker may use (never an OOM kill)."""
    monkeypatch.setenv("FPM_WORKER_MEMORY", "1M")
    created = api.post("/v1/calibrations", json=small_spec)
    assert created.status_code == 202, created.text
    for _ in range(5):  # each retry is a refusal; run until nothing is queued
        run_workers()
    status = api.get(f"/v1/calibrations/{created.json()['id']}").json()
    assert status["status"] == "failed"
    assert "needs about" in status["error"] and "FPM_WORKER_MEMORY" in status["error"]
