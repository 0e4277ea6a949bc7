"""Faults done for real: Redis killed and restarted, diverging specs, timeouts, cancels.

Each test runs the real API in-process against a real redis-server and real ``python -m worker``
processes (or the in-process burst worker where the damage is in the job, not the process). The
worker killed mid-chain (retry + checkpoint resume) is in tests/service/test_worker.py; the worker
killed during the reduced-basis job and during the damping stage is here.
"""

from __future__ import annotations

import copy
import os
import signal
import time
from collections.abc import Callable, Iterator

import pytest
from conftest import WorkerProcesses
from fastapi.testclient import TestClient
from redis import Redis
from rq.job import Job, JobStatus
from rq.registry import CanceledJobRegistry, StartedJobRegistry
from rq.serializers import JSONSerializer
from test_service import assert_problem
from test_worker import alive, child_pids

import fpm
from fpm.fitting.calibration import calibrate
from service.main import create_app
from service.settings import Settings
from stack.redis_server import RedisServer
from store import graph, keys, records, scratch
from store.status import CalibrationStatus

pytestmark = pytest.mark.redis


def wait_for(predicate: Callable[[], object], timeout: float = 30.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what or predicate}"
        time.sleep(0.05)


def status_of(api: TestClient, calibration_id: str) -> dict:
    response = api.get(f"/v1/calibrations/{calibration_id}")
    assert response.status_code == 200, response.text
    return response.json()


def wait_until_done(api: TestClient, calibration_id: str, timeout: float = 30.0) -> dict:
    """Poll the API until the calibration is terminal; returns its last answer."""
    seen: dict = {}

    def done() -> bool:
        seen.update(status_of(api, calibration_id))
        return seen["status"] in ("succeeded", "failed", "canceled")

    wait_for(done, timeout, f"calibration {calibration_id}")
    return seen


def assert_no_work_left(redis: Redis, worker_count: int = 1) -> None:
    """Nothing running, queued or waiting: no orphaned job survives the fault."""
    for q in graph.queues(redis):
        wait_for(lambda q=q: q.started_job_registry.count == 0, 20, "the started registry to empty")
        assert q.count == 0, q.get_job_ids()
        assert q.deferred_job_registry.count == 0, q.deferred_job_registry.get_job_ids()


# --- Redis stopped and restarted (append-only file on) ------------------------------------------


@pytest.fixture
def durable_redis(tmp_path) -> Iterator[RedisServer]:
    """A redis-server of this test's own with the append-only file on (in tmp_path)."""
    server = RedisServer(data_dir=tmp_path / "redis").start()
    yield server
    server.stop()


def test_redis_crash_loses_nothing_and_everyone_recovers(durable_redis, small_spec):
    settings = Settings(redis_url=durable_redis.url, redis_timeout=0.5, max_chains=4)
    workers = WorkerProcesses(durable_redis.url)
    worker = workers.start()
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as api:
            submitted = api.post("/v1/calibrations", json=small_spec)
            assert submitted.status_code == 202
            calibration_id = submitted.json()["id"]
            before = wait_until_done(api, calibration_id, timeout=60)  # a cold kernel cache
            assert before["status"] == "succeeded", before["error"]
            ps_id = before["parameter_set_id"]
            parameter_set = api.get(f"/v1/parameter-sets/{ps_id}").json()
            fem = api.get(f"/v1/fem-references/{before['fem_reference_id']}").json()

            durable_redis.stop(kill=True)  # SIGKILL: a crash, no shutdown save
            down_started = time.monotonic()
            small_spec["annealing"]["seed"] = 8
            for method, path, body in [
                ("GET", "/v1/health", None),
                ("GET", f"/v1/calibrations/{calibration_id}", None),
                ("GET", "/v1/calibrations", None),
                ("DELETE", f"/v1/calibrations/{calibration_id}", None),
                ("GET", f"/v1/parameter-sets/{ps_id}", None),
                ("GET", "/v1/parameter-sets", None),
                ("GET", f"/v1/fem-references/{fem['id']}", None),
                ("POST", "/v1/calibrations", small_spec),
                ("POST", "/v1/fem-references", small_spec),
            ]:
                answer = api.request(method, path, json=body)
                problem = assert_problem(answer, 503)
                assert "Redis" in problem["detail"] and answer.headers["retry-after"]
            # Nine requests, each refused quickly: no hang on a dead socket.
            assert time.monotonic() - down_started < 9 * 2 * settings.redis_timeout + 2

            durable_redis.start()  # same port, same directory: replays the append-only file
            # The API recovers by itself (same app, same connection pool).
            health = api.get("/v1/health")
            assert health.status_code == 200 and health.json()["redis"] is True
            after = status_of(api, calibration_id)
            assert after["status"] == "succeeded" and after["result"] == before["result"]
            assert api.get(f"/v1/parameter-sets/{ps_id}").json() == parameter_set
            assert api.get("/v1/parameter-sets").json()["total"] == 1
            assert api.get(f"/v1/fem-references/{fem['id']}").json() == fem
            # The same worker process reconnects and runs the next calibration.
            again = api.post("/v1/calibrations", json=small_spec)
            assert again.status_code == 202
            second = wait_until_done(api, again.json()["id"], timeout=60)
            assert second["status"] == "succeeded", second["error"]
            assert second["fem_cached"] is True  # the stored FEM reference survived too
            assert worker.poll() is None
            assert api.get("/v1/parameter-sets").json()["total"] == 2
            assert_no_work_left(Redis.from_url(durable_redis.url))
    finally:
        for process in workers.started:
            workers.stop(process)


# --- A calibration that cannot be fitted --------------------------------------------------------


@pytest.mark.parametrize("method", ["two-stage", "paper"])
@pytest.mark.parametrize(
    "change",
    [
        pytest.param(lambda s: s["fpm"].update(dt=10.0), id="dt-far-too-large"),
        pytest.param(
            lambda s: s["annealing"].update(bounds={"d": [1e-9, 2e-9]}), id="tiny-damping"
        ),
    ],
)
def test_all_candidates_diverge_fails_with_a_reason(
    api, redis, run_workers, small_spec, change, method
):
    change(small_spec)
    small_spec["annealing"]["method"] = method
    calibration_id = api.post("/v1/calibrations", json=small_spec).json()["id"]
    run_workers()
    done = status_of(api, calibration_id)
    assert done["status"] == "failed" and done["result"] is None
    error = done["error"]
    if method == "paper":  # every (k, d) the annealer tries diverges
        assert "no acceptable starting point" in error and "diverged" in error, error
        assert "lower fpm.dt" in error or "annealing.bounds.d" in error  # what to do
        failing = [keys.chain_job_id(calibration_id, c) for c in range(2)]
    else:  # the static stiffness search succeeds; no d settles the dynamic runs
        assert error.startswith("damping stage failed: no d in"), error
        assert "lower fpm.dt" in error
        assert done["progress"]["phase"] == "damping"
        failing = [keys.damping_job_id(calibration_id)]
    assert "Traceback" not in error
    assert done["parameter_set_id"] is None and redis.zcard(keys.parameter_sets()) == 0
    # Not retried: the same spec fails the same way, so the failing job ran once.
    for job_id in failing:
        job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
        assert job.get_status() == JobStatus.FINISHED and job.retries_left == 2
    assert all(q.failed_job_registry.count == 0 for q in graph.queues(redis))
    assert_no_work_left(redis)


# --- Timeouts -----------------------------------------------------------------------------------


def slow(spec: dict, beta: float = 0.2) -> dict:
    """One chain of ~2400 moves: many seconds, far more than the timeouts below."""
    spec["annealing"].update(chains=1, beta=beta, t_final=0.002, seed=11)
    return spec


def test_timed_out_chain_fails_cleanly_and_frees_its_worker(
    settings, redis, worker_processes, small_spec
):
    limited = settings.model_copy(update={"chain_timeout": 2, "job_retries": 0})
    worker = worker_processes.start()
    with TestClient(create_app(limited), raise_server_exceptions=False) as api:
        long_one = api.post("/v1/calibrations", json=slow(small_spec)).json()["id"]
        started = time.monotonic()
        failed = wait_until_done(api, long_one, timeout=30)
        assert failed["status"] == "failed", failed
        assert "timeout" in failed["error"].lower() and "2 seconds" in failed["error"]
        assert time.monotonic() - started < 20
        chain = Job.fetch(
            keys.chain_job_id(long_one, 0), connection=redis, serializer=JSONSerializer
        )
        # The failure callback marks the calibration before RQ marks the job.
        wait_for(lambda: chain.get_status() == JobStatus.FAILED, 10, "the chain job to fail")
        # The worker is free again: the next calibration runs on the same process.
        small_spec["annealing"].update(beta=10, chains=2)
        quick = api.post("/v1/calibrations", json=small_spec).json()["id"]
        done = wait_until_done(api, quick, timeout=30)
        assert done["status"] == "succeeded", done["error"]
        assert worker.poll() is None
        assert_no_work_left(redis)


# --- Cancel in each phase -----------------------------------------------------------------------


def big_fem(spec: dict) -> dict:
    """A 25^3-node box: its FEM reference takes a couple of seconds."""
    spec["geometry"]["nodes"] = [25, 25, 25]
    return spec


def slow_damping(spec: dict) -> dict:
    """The small spec with a damping stage of a second or two (dt 2e-5 s: ~50x the steps)."""
    spec["fpm"].update(dt=2e-5, max_steps=100_000)
    return spec


def in_damping(api: TestClient, calibration_id: str) -> Callable[[], bool]:
    """True once the calibration reports the damping stage's d search."""

    def check() -> bool:
        p = status_of(api, calibration_id)["progress"]
        return p["phase"] == "damping" and (p["damping"] or {}).get("step") == "damping"

    return check


@pytest.mark.parametrize("phase", ["fem", "annealing", "damping"])
def test_cancel_in_each_phase_leaves_no_job_running(
    settings, redis, worker_processes, small_spec, phase
):
    roomy = settings.model_copy(update={"max_nodes": 20_000})
    spec = {"fem": big_fem, "annealing": slow, "damping": slow_damping}[phase](small_spec)
    spec["annealing"]["chains"] = 2
    worker_processes.start()
    with TestClient(create_app(roomy), raise_server_exceptions=False) as api:
        calibration_id = api.post("/v1/calibrations", json=spec).json()["id"]

        def in_phase() -> bool:
            view = status_of(api, calibration_id)
            moved = any(c["move"] > 3 for c in view["progress"]["chains"])
            return view["progress"]["phase"] == phase and (phase == "fem" or moved)

        wait_for(in_damping(api, calibration_id) if phase == "damping" else in_phase, 60, phase)
        canceled = api.delete(f"/v1/calibrations/{calibration_id}")
        assert canceled.status_code == 200 and canceled.json()["status"] == "canceled"
        assert_no_work_left(redis)  # the FEM job (shared) finishes; nothing else runs
        # A job the cancel stopped is no failure (RQ files it as failed, status stopped).
        assert api.get("/v1/health").json()["failed_jobs"] == 0
        view = status_of(api, calibration_id)
        assert view["status"] == "canceled" and view["result"] is None
        assert redis.zcard(keys.parameter_sets()) == 0
        chain_ids = [keys.chain_job_id(calibration_id, c) for c in range(2)]
        damping_id, finalize_id = (
            keys.damping_job_id(calibration_id),
            keys.finalize_job_id(calibration_id),
        )
        jobs = {
            job.id: job.get_status()
            for job in Job.fetch_many(
                [*chain_ids, damping_id, finalize_id],
                connection=redis,
                serializer=JSONSerializer,
            )
        }
        assert jobs[finalize_id] == JobStatus.CANCELED
        if phase == "fem":  # no chain ever started
            assert set(jobs.values()) == {JobStatus.CANCELED}
            assert view["progress"]["chains"] == []
        elif phase == "annealing":  # one chain was stopped mid-way, the other never started
            (running,) = view["progress"]["chains"]
            assert 3 < running["move"] < running["moves"]
            chains = sorted(jobs[c] for c in chain_ids)
            assert chains == [JobStatus.CANCELED, JobStatus.STOPPED]
            assert jobs[damping_id] == JobStatus.CANCELED
        else:  # the chains finished; the damping job was stopped mid-way
            assert [jobs[c] for c in chain_ids] == [JobStatus.FINISHED] * 2
            assert jobs[damping_id] == JobStatus.STOPPED
            assert view["progress"]["phase"] == "damping"
            assert not redis.exists(keys.damping_result(calibration_id))
        if phase != "damping":
            for c in range(2):
                assert not redis.exists(keys.chain_result(calibration_id, c))
        registry = CanceledJobRegistry(
            keys.PRIORITY_QUEUE, connection=redis, serializer=JSONSerializer
        )
        assert finalize_id in registry.get_job_ids()


# --- A worker killed during the damping stage ---------------------------------------------------


def test_worker_killed_in_the_damping_stage_is_retried(
    settings, redis, worker_processes, small_spec
):
    spec = slow_damping(small_spec)
    first = worker_processes.start()
    with TestClient(create_app(settings), raise_server_exceptions=False) as api:
        calibration_id = api.post("/v1/calibrations", json=spec).json()["id"]
        wait_for(in_damping(api, calibration_id), 60, "the damping stage")
        view = status_of(api, calibration_id)
        progress = view["progress"]
        assert progress["stages"] == ["fem", "annealing", "damping", "finalize"]
        assert progress["stage"].startswith("stage 3 of 4: damping")
        assert progress["iterations"] == progress["total_iterations"]  # the chains are done
        (horse,) = child_pids(first.pid)
        os.kill(first.pid, signal.SIGKILL)  # the worker dies; its work horse with it
        first.wait()
        wait_for(lambda: not alive(horse), 5, "the work horse to die")
        damping_id = keys.damping_job_id(calibration_id)
        registry = StartedJobRegistry(
            keys.PRIORITY_QUEUE, connection=redis, serializer=JSONSerializer
        )
        assert damping_id in registry.get_job_ids(cleanup=False)
        # What RQ's maintenance does once the dead worker's heartbeat has expired:
        registry.cleanup(timestamp=time.time() + 3600)
        job = Job.fetch(damping_id, connection=redis, serializer=JSONSerializer)
        assert job.get_status() == JobStatus.QUEUED and job.retries_left == 1
        assert status_of(api, calibration_id)["status"] == "running"

        worker_processes.start()  # another worker takes the retry
        done = wait_until_done(api, calibration_id, timeout=60)
        assert done["status"] == "succeeded", done["error"]
        assert done["progress"]["phase"] == "done"
        expected = calibrate(fpm.load_problem(spec))  # uninterrupted, in-process
        for name in ("k", "d", "d_min", "depth", "relative_discrepancy", "settle_steps"):
            assert done["result"][name] == pytest.approx(expected.to_dict()[name], rel=1e-12)
        assert api.get("/v1/parameter-sets").json()["total"] == 1
        assert not redis.exists(keys.damping_result(calibration_id))
        assert_no_work_left(redis)


# --- A worker killed during the reduced-basis job -----------------------------------------------


def test_worker_killed_in_the_reduced_basis_job_is_retried(redis, worker_processes, small_spec):
    """families+volume on a 22^3-node box (its first basis about a second): the worker dies
    while it builds the basis, before it is stored; the job is re-queued, another worker
    builds it and the calibration ends with the uninterrupted in-process answer, to the bit."""
    from test_worker import submit

    spec = copy.deepcopy(small_spec)
    spec["geometry"]["nodes"] = [22, 22, 22]
    spec["fpm"].update(stiffness="families+volume", dt="auto", max_steps="auto", depth="auto")
    record, _ = submit(redis, spec)
    basis_id = keys.basis_job_id(record.id)
    registry = StartedJobRegistry(keys.QUEUE, connection=redis, serializer=JSONSerializer)
    first = worker_processes.start()
    job = Job.fetch(basis_id, connection=redis, serializer=JSONSerializer)
    wait_for(lambda: job.get_status() == JobStatus.STARTED, 60, "the basis job")
    wait_for(lambda: child_pids(first.pid), 5, "its work horse")
    time.sleep(0.2)  # into the build (about a second)
    (horse,) = child_pids(first.pid)
    os.kill(first.pid, signal.SIGKILL)  # the worker dies; its work horse with it
    first.wait()
    wait_for(lambda: not alive(horse), 5, "the work horse to die")
    assert not scratch.has_reduced_basis(redis, record.id)  # killed before it stored it
    assert basis_id in registry.get_job_ids(cleanup=False)
    registry.cleanup(timestamp=time.time() + 3600)  # RQ's maintenance, the heartbeat expired
    job = Job.fetch(basis_id, connection=redis, serializer=JSONSerializer)
    assert job.get_status() == JobStatus.QUEUED and job.retries_left == 0
    worker_processes.start()  # another worker takes the retry
    wait_for(lambda: records.get_calibration(redis, record.id).status.terminal, 120, "the end")
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    expected = calibrate(fpm.load_problem(spec))
    for name in ("stiffness", "volume_stiffness", "d", "d_min", "depth", "settle_steps"):
        assert done.result[name] == expected.to_dict()[name], name
    assert [s["name"] for s in done.result["jobs"]].count("reduced basis") == 1
    assert not redis.exists(keys.reduced_basis(record.id))
    assert_no_work_left(redis)


# --- Workers and Redis killed while seeded calibrations run ------------------------------------


def test_workers_and_redis_killed_mid_run_give_the_undisturbed_answers(durable_redis, small_spec):
    """Two seeded calibrations; while they run, a worker is SIGKILLed, then Redis is SIGKILLed
    and restarted (append-only file), then the dead worker's jobs are requeued as RQ's
    maintenance does and a fresh worker finishes them: each ends with exactly the (k, d, depth)
    and figures of an undisturbed in-process run, and one parameter set each."""
    settings = Settings(redis_url=durable_redis.url, redis_timeout=0.5, max_chains=4)
    specs = []
    for seed in (5, 6):
        spec = slow_damping(copy.deepcopy(small_spec))
        spec["annealing"]["seed"] = seed
        specs.append(spec)
    workers = WorkerProcesses(durable_redis.url)
    first = workers.start()
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as api:
            ids = [api.post("/v1/calibrations", json=s).json()["id"] for s in specs]
            wait_for(in_damping(api, ids[0]), 90, "the first calibration's damping stage")
            os.kill(first.pid, signal.SIGKILL)  # the worker dies mid-job
            first.wait()
            durable_redis.stop(kill=True)  # and Redis crashes
            durable_redis.start()  # replays its append-only file
            redis = Redis.from_url(durable_redis.url)
            wait_for(lambda: api.get("/v1/health").status_code == 200, 20, "the API to recover")
            for name in (keys.QUEUE, keys.PRIORITY_QUEUE):  # RQ's maintenance, now
                StartedJobRegistry(name, connection=redis, serializer=JSONSerializer).cleanup(
                    timestamp=time.time() + 3600
                )
            workers.start()
            done = [wait_until_done(api, i, timeout=180) for i in ids]
            for spec, answer in zip(specs, done, strict=True):
                assert answer["status"] == "succeeded", answer["error"]
                expected = calibrate(fpm.load_problem(spec))  # undisturbed, in-process
                for name in ("k", "d", "depth", "relative_discrepancy", "settle_steps"):
                    assert answer["result"][name] == pytest.approx(
                        expected.to_dict()[name], rel=1e-12
                    ), name
            assert api.get("/v1/parameter-sets").json()["total"] == 2
            assert_no_work_left(redis)
    finally:
        for process in workers.started:
            workers.stop(process)
