"""Outages, against real processes: a dead worker's job is re-queued within a
minute, busy workers ride out a Redis outage, and the local stack restarts what dies."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from conftest import WorkerProcesses
from fastapi.testclient import TestClient
from redis import Redis
from redis.exceptions import RedisError
from rq import Worker
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer
from test_faults import assert_no_work_left, status_of, wait_for, wait_until_done
from test_worker import alive, child_pids, slow_spec, submit

from service.main import create_app
from service.settings import Settings
from stack.local import LocalStack
from stack.redis_server import RedisServer, free_port
from store import keys, records, timing
from store.status import CalibrationStatus

pytestmark = pytest.mark.redis

SHORT_TTL = 6
"""The worker TTL of the re-queue test (FPM_WORKER_TTL): its bound is seconds, not minutes."""


def registered(redis: Redis, process) -> Worker | None:
    """The RQ worker registered by ``process``, once it listens."""
    for w in Worker.all(connection=redis):
        if w.pid == process.pid:
            return w
    return None


# --- 4. a dead worker's job re-queued within a minute --------------------------------------------


def test_requeue_bound_of_the_default_timing_is_under_a_minute(monkeypatch):
    monkeypatch.delenv("FPM_WORKER_TTL", raising=False)
    default = timing._ttl_from_environment()
    assert (default, timing.requeue_bound(default)) == (30, 40)
    assert timing.requeue_bound(SHORT_TTL) == 8
    for ttl in (timing.MIN_TTL, SHORT_TTL, default, 420):
        # A busy worker beats three times within the health window, an idle one twice.
        assert 3 * timing.job_monitoring_interval(ttl) <= ttl
        assert 2 * timing.dequeue_timeout(ttl) <= ttl
        assert timing.maintenance_interval(ttl) < timing.dequeue_timeout(ttl)
    monkeypatch.setenv("FPM_WORKER_TTL", "3")
    with pytest.raises(ValueError, match="at least 4"):
        timing._ttl_from_environment()


def test_job_of_a_killed_worker_is_picked_up_within_a_minute(
    redis, worker_processes, small_spec, monkeypatch
):
    monkeypatch.setenv("FPM_WORKER_TTL", str(SHORT_TTL))  # the workers inherit it
    pair = [worker_processes.start(), worker_processes.start()]
    wait_for(lambda: all(registered(redis, p) for p in pair), 60, "both workers to listen")
    record, _ = submit(redis, slow_spec(small_spec, beta=0.1))  # one chain of ~4800 moves
    chain = Job.fetch(keys.chain_job_id(record.id, 0), connection=redis, serializer=JSONSerializer)
    wait_for(lambda: records.get_progress(redis, record.id).get(0, {}).get("move", 0) > 5, 30)
    chain.refresh()
    busy, idle = sorted(pair, key=lambda p: registered(redis, p).name != chain.worker_name)
    idle_name = registered(redis, idle).name
    (horse,) = child_pids(busy.pid)
    os.kill(busy.pid, signal.SIGKILL)  # no chance to hand the job back; its horse dies with it
    killed = time.monotonic()
    busy.wait()
    wait_for(lambda: not alive(horse), 5, "the work horse to die")

    def picked_up_again() -> bool:
        chain.refresh()
        return chain.get_status() == JobStatus.STARTED and chain.worker_name == idle_name

    wait_for(picked_up_again, 60, "the chain to be picked up again")
    after = time.monotonic() - killed
    print(f"re-queued and picked up {after:.1f} s after the kill (TTL {SHORT_TTL} s)")
    # The bound is the design's; the slack covers process scheduling on a loaded 2-core
    # machine (a full suite at load average 10 once took the bound + 1.04 s).
    assert after < timing.requeue_bound(SHORT_TTL) + 3 < 60
    assert chain.retries_left == 0  # the retry (submit gives one) was spent on it
    wait_for(
        lambda: records.get_calibration(redis, record.id).status.terminal, 60, "the calibration"
    )
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    assert idle.poll() is None


# --- 5. busy workers ride out a Redis outage ----------------------------------------------------


@pytest.fixture
def durable_redis(tmp_path) -> Iterator[RedisServer]:
    """A redis-server of this test's own on a free port, append-only file in tmp_path."""
    server = RedisServer(data_dir=tmp_path / "redis").start()
    yield server
    server.stop()


def moves(api: TestClient, calibration_id: str) -> list[int]:
    return [c["move"] for c in status_of(api, calibration_id)["progress"]["chains"]]


def test_busy_workers_ride_out_a_redis_outage(durable_redis, small_spec):
    settings = Settings(redis_url=durable_redis.url, redis_timeout=0.5, max_chains=4)
    workers = WorkerProcesses(durable_redis.url)
    pair = [workers.start(), workers.start()]
    spec = slow_spec(small_spec, beta=0.2)  # chains of ~2400 moves: seconds each
    spec["annealing"]["chains"] = 2
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as api:
            calibration_id = api.post("/v1/calibrations", json=spec).json()["id"]

            def both_annealing() -> bool:
                return len(moves(api, calibration_id)) == 2 and min(moves(api, calibration_id)) > 5

            wait_for(both_annealing, 60, "both chains to anneal")
            assert all(len(child_pids(p.pid)) == 1 for p in pair)  # both workers busy
            before = moves(api, calibration_id)
            durable_redis.stop(kill=True)  # SIGKILL: a crash
            time.sleep(2)
            durable_redis.start()  # same port, same data directory
            back = time.monotonic()
            wait_for(
                lambda: all(a > b for a, b in zip(moves(api, calibration_id), before, strict=True)),
                30,
                "both chains to go on",
            )
            recovery = time.monotonic() - back
            print(f"both chains went on {recovery:.1f} s after Redis came back")
            assert recovery < 5
            assert all(p.poll() is None for p in pair)  # no worker quit
            done = wait_until_done(api, calibration_id, timeout=120)
            assert done["status"] == "succeeded", done["error"]
            assert all(p.poll() is None for p in pair)
            redis = Redis.from_url(durable_redis.url)
            for c in range(2):  # kept through the outage, not re-queued
                job = Job.fetch(
                    keys.chain_job_id(calibration_id, c),
                    connection=redis,
                    serializer=JSONSerializer,
                )
                assert job.get_status() == JobStatus.FINISHED and job.retries_left == 2
            assert api.get("/v1/parameter-sets").json()["total"] == 1
            assert_no_work_left(redis)
    finally:
        for process in workers.started:
            workers.stop(process)


# --- 5. the local stack restarts what dies ------------------------------------------------------


def answers(redis: Redis) -> bool:
    try:
        return bool(redis.ping())
    except RedisError:
        return False


def _on_disk(folder: Path, needle: bytes) -> bool:
    """Whether an append-only file under ``folder`` (Redis 7's pieces or an older single file)
    holds ``needle``."""
    return any(needle in p.read_bytes() for p in folder.rglob("*aof*") if p.is_file())


def test_local_stack_restarts_a_dead_worker_and_redis(tmp_path):
    with LocalStack(
        workers=1, port=free_port(), data_dir=tmp_path / "data", log_dir=tmp_path / "logs"
    ) as stack:
        assert stack.redis is not None
        redis = Redis.from_url(stack.redis_url)
        (worker,) = stack.workers
        first = worker.process
        os.killpg(first.pid, signal.SIGKILL)
        killed = time.monotonic()
        wait_for(lambda: worker.process is not first, 5, "the worker to be restarted")
        wait_for(lambda: registered(redis, worker.process), 30, "the new worker to listen")
        print(f"worker restarted {time.monotonic() - killed:.1f} s after the kill")

        redis.set("fpm:outage-test", "kept")
        # The append-only file is fsynced every second: a write younger than that may die with
        # the process (Redis's own guarantee), so the kill waits for it to be on disk.
        data = stack.redis.data_dir
        wait_for(lambda: _on_disk(data, b"outage-test"), 10, "the write to reach the AOF")
        port, server = stack.redis.port, stack.redis.process
        assert server is not None
        server.kill()
        wait_for(lambda: stack.redis.process not in (None, server), 5, "Redis to be restarted")
        assert stack.redis.port == port
        wait_for(lambda: answers(redis), 10, "the restarted Redis to answer")  # loaded machines
        assert redis.get("fpm:outage-test") == b"kept"  # same data directory
        health = httpx.get(f"{stack.url}/v1/health", timeout=5).json()
        assert health["redis"] is True
        assert worker.process.poll() is None
        # The supervisor counts the restart once its start returns, which polls Redis too: the
        # test's own ping may win that race by a poll interval.
        wait_for(lambda: "redis" in stack.restarts, 5, "the restart to be counted")
        assert stack.restarts == {"worker-0": 1, "redis": 1}
