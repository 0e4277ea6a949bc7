"""The job graph against a real Redis and real RQ workers."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from rq.job import Job, JobStatus
from rq.registry import StartedJobRegistry
from rq.serializers import JSONSerializer

import fpm
from fpm.fitting.calibration import calibrate
from fpm.fitting.cost import StaticCost
from fpm.fitting.result import ChainSummary
from service.limits import dump_spec
from store import graph, keys, records
from store.hashing import fem_hash, spec_hash
from store.status import CalibrationStatus
from worker.jobs import basis as basis_job
from worker.jobs import chains as chain_jobs

pytestmark = pytest.mark.redis


def submit(redis, spec):
    """Validate like the service does, then submit."""
    dumped = dump_spec(fpm.load_problem(spec).spec)
    return graph.submit_calibration(redis, dumped, graph.JobOptions(retries=1))


def wait_for(predicate, timeout=20.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_result_equals_in_process_calibration(redis, run_workers, small_spec):
    record, created = submit(redis, small_spec)
    assert created and record.status == CalibrationStatus.QUEUED
    run_workers()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    expected = calibrate(fpm.load_problem(small_spec))
    assert done.result["method"] == expected.method == "two-stage"
    for name in (
        "k",
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
        "evaluations",
        "damping_runs",
        "h",
    ):
        assert done.result[name] == pytest.approx(expected.to_dict()[name], rel=1e-12), name
    assert done.result["stiffness"] == pytest.approx(expected.parameters.stiffness, rel=1e-12)
    assert set(done.result["seconds"]) == {"stiffness", "damping", "finalize"}
    # Stored for good (no TTL): the FEM reference, the parameter set, the record.
    for key in (
        keys.fem_reference(record.fem_hash),
        keys.parameter_set(done.parameter_set_id),
        keys.calibration(record.id),
    ):
        assert redis.ttl(key) == -1
    # Scratch is gone or expiring.
    assert not redis.exists(keys.chain_checkpoint(record.id, 0))
    assert not redis.exists(keys.damping_result(record.id))
    assert redis.ttl(keys.chain_result(record.id, 0)) > 0
    assert redis.ttl(keys.calibration_progress(record.id)) > 0
    # Each chain's summary has the fields the answer's schema documents.
    assert set(done.result["chains"][0]) == set(ChainSummary.model_fields)
    # The parameter set carries what the worker promises (service/schemas.py ParameterSet).
    ps = records.get_parameter_set(redis, done.parameter_set_id)
    for name in ("k", "stiffness", "d", "d_min", "depth", "relative_discrepancy", "node_mass"):
        assert ps[name] == done.result[name], name
    assert ps["stiffness_mode"] == "single" and ps["dt"] == small_spec["fpm"].get("dt", 1e-3)
    assert ps["geometry"] == {
        "type": "box",
        "connectivity": "full",
        "size": small_spec["geometry"]["size"],
        "nodes": 64,
        "h": done.result["h"],
    }
    assert ps["provenance"]["method"] == "two-stage"


def graph_of(redis, record):
    """{job id: (function, ids of the jobs it waits for)} of a calibration's jobs."""
    ids = [keys.fem_job_id(record.fem_hash)]
    ids += [keys.chain_job_id(record.id, c) for c in range(record.chains)]
    ids += [keys.damping_job_id(record.id), keys.finalize_job_id(record.id)]
    jobs = Job.fetch_many(ids, connection=redis, serializer=JSONSerializer)
    return {j.id: (j.func_name, sorted(j.dependency_ids)) for j in jobs if j is not None}


@pytest.mark.parametrize("method", ["two-stage", "paper"])
def test_job_graph_of_each_method(redis, run_workers, small_spec, method):
    small_spec["annealing"]["method"] = method
    record, _ = submit(redis, small_spec)
    fem = keys.fem_job_id(record.fem_hash)
    chains = [keys.chain_job_id(record.id, c) for c in range(2)]
    expected = {
        fem: (keys.FEM_JOB, []),
        chains[0]: (keys.CHAIN_JOB, [fem]),
        chains[1]: (keys.CHAIN_JOB, [fem]),
    }
    if method == "two-stage":  # fem -> chains -> damping -> finalize
        damping = keys.damping_job_id(record.id)
        expected[damping] = (keys.DAMPING_JOB, sorted(chains))
        expected[keys.finalize_job_id(record.id)] = (keys.FINALIZE_JOB, [damping])
    else:  # fem -> chains -> finalize: no damping job
        expected[keys.finalize_job_id(record.id)] = (
            keys.FINALIZE_JOB,
            sorted(chains),
        )
    assert graph_of(redis, record) == expected
    run_workers()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    assert done.result["method"] == method
    expected_result = calibrate(fpm.load_problem(small_spec))
    assert (done.result["k"], done.result["d"]) == pytest.approx(
        (expected_result.parameters.k, expected_result.parameters.d), rel=1e-12
    )
    chain_results = [json.loads(redis.get(keys.chain_result(record.id, c))) for c in range(2)]
    n = 1 if method == "two-stage" else 2  # stiffness parameters, plus d for paper
    assert [len(c["x"]) for c in chain_results] == [n, n]
    damping = records.get_damping_progress(redis, record.id)
    if method == "two-stage":
        assert done.result["d_min"] is not None and done.result["damping_runs"] > 0
        assert damping["step"] == "damping" and damping["runs"] > 0
        assert damping["best_d"] == pytest.approx(done.result["d"], rel=1e-12)
    else:
        assert done.result["d_min"] is None and done.result["damping_runs"] == 0
        assert damping is None


def test_families_volume_builds_its_reduced_basis_once_beside_the_fem(
    redis, run_workers, small_spec, monkeypatch
):
    """families+volume: the reduced-basis job waits for nothing, the chains for it and the FEM
    job; it alone builds the first basis, which each chain and the damping job read back (none
    builds it again); the answer equals the in-process calibration's to the bit; the timeline
    has its span, the chains after it; finalize drops the stored basis."""
    import fpm.fitting.damping.polish as damping_stage
    import fpm.fitting.stiffness_stage as stiffness_stage

    small_spec["fpm"].update(stiffness="families+volume", dt="auto", max_steps="auto")
    record, _ = submit(redis, small_spec)
    fem, basis = keys.fem_job_id(record.fem_hash), keys.basis_job_id(record.id)
    chains = [keys.chain_job_id(record.id, c) for c in range(2)]
    jobs = Job.fetch_many([fem, basis, *chains], connection=redis, serializer=JSONSerializer)
    assert {j.id: (j.func_name, sorted(j.dependency_ids)) for j in jobs} == {
        fem: (keys.FEM_JOB, []),
        basis: (keys.BASIS_JOB, []),
        chains[0]: (keys.CHAIN_JOB, sorted([fem, basis])),
        chains[1]: (keys.CHAIN_JOB, sorted([fem, basis])),
    }
    built: list[str] = []
    for module in (basis_job, stiffness_stage, damping_stage):

        def counted(problem, real=module.first_basis, name=module.__name__):
            built.append(name)
            return real(problem)

        monkeypatch.setattr(module, "first_basis", counted)
    given = []
    real_run_chain = chain_jobs.run_chain

    def recording_run_chain(problem, reference, chain, **kw):
        given.append(kw["basis"])
        return real_run_chain(problem, reference, chain, **kw)

    monkeypatch.setattr(chain_jobs, "run_chain", recording_run_chain)
    run_workers()
    monkeypatch.undo()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    assert built == ["worker.jobs.basis"] and len(given) == 2 and None not in given
    expected = calibrate(fpm.load_problem(small_spec))
    for name in ("stiffness", "volume_stiffness", "d", "d_min", "depth", "cost", "static_cost",
                 "relative_discrepancy", "settle_steps", "evaluations"):  # fmt: skip
        assert done.result[name] == expected.to_dict()[name], name
    assert not redis.exists(keys.reduced_basis(record.id))
    spans = {s["name"]: s for s in done.result["jobs"]}
    assert spans["reduced basis"]["after"] == []
    assert "reduced basis" in spans["chain 0"]["after"]
    assert spans["reduced basis"]["cpu"] >= 0 and spans["reduced basis"]["worker"]


def test_identical_spec_returns_the_same_calibration(redis, run_workers, small_spec):
    first, _ = submit(redis, small_spec)
    again, created = submit(redis, small_spec)
    assert not created and again.id == first.id
    run_workers()
    done, created = submit(redis, small_spec)
    assert not created and done.id == first.id and done.status == CalibrationStatus.SUCCEEDED


def test_second_calibration_reuses_the_stored_fem_reference(redis, run_workers, small_spec):
    first, _ = submit(redis, small_spec)
    assert not first.fem_cached
    run_workers()
    small_spec["annealing"]["seed"] = 4  # another calibration, the same FEM reference
    second, created = submit(redis, small_spec)
    assert created and second.fem_cached and second.fem_hash == first.fem_hash
    queued = (
        graph.queue(redis).get_job_ids() + graph.queue(redis).deferred_job_registry.get_job_ids()
    )
    assert not any(job_id.startswith("fem-") for job_id in queued)
    run_workers()
    assert records.get_calibration(redis, second.id).status == CalibrationStatus.SUCCEEDED
    assert redis.zcard(keys.parameter_sets()) == 2


def test_finalize_twice_stores_one_parameter_set(redis, run_workers, small_spec):
    record, _ = submit(redis, small_spec)
    run_workers()
    ps_id = records.get_calibration(redis, record.id).parameter_set_id
    stored = redis.get(keys.parameter_set(ps_id))
    # A retried finalize (e.g. its worker died after writing) changes nothing.
    redis.hset(keys.calibration(record.id), "status", CalibrationStatus.RUNNING.value)
    graph.queue(redis).enqueue_call(keys.FINALIZE_JOB, args=(record.id,))
    run_workers()
    assert redis.zcard(keys.parameter_sets()) == 1
    assert redis.get(keys.parameter_set(ps_id)) == stored


def test_a_refined_reference_writes_its_levels_for_the_progress(redis, run_workers, small_spec):
    small_spec["reference"] = {"refine": 1}  # levels 0 and 1 of the 8-node reference
    record, _ = submit(redis, small_spec)
    run_workers()
    meta = records.get_fem_meta(redis, record.fem_hash)
    assert meta["status"] == "succeeded" and meta["level"] == "1"
    assert int(meta["fem_nodes"]) > int(meta["n_nodes"])  # the refined mesh, not the lattice


def test_fem_failure_fails_the_calibration(redis, run_workers, small_spec):
    small_spec["fixed"] = [{"node": 0}]  # one node cannot hold the solid: the FEM refuses
    record, _ = submit(redis, small_spec)
    run_workers()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.FAILED
    assert "FEM" in done.error
    assert records.get_fem_meta(redis, record.fem_hash)["status"] == "failed"


def test_cancel_queued_calibration(redis, run_workers, small_spec):
    record, _ = submit(redis, small_spec)
    assert graph.cancel_calibration(redis, record.id)
    assert not graph.cancel_calibration(redis, record.id)  # already canceled
    run_workers()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.CANCELED and done.result is None
    assert redis.zcard(keys.parameter_sets()) == 0
    for job_id in (keys.damping_job_id(record.id), keys.finalize_job_id(record.id)):
        job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
        assert job.get_status() == JobStatus.CANCELED, job_id


def slow_spec(spec, beta=1.5):
    """The small spec with one chain of ~480 / beta moves (~320: a second or so)."""
    spec["annealing"].update(chains=1, beta=beta, t_final=0.002, seed=11)
    return spec


def test_cancel_stops_a_running_chain(redis, worker_processes, small_spec):
    record, _ = submit(redis, slow_spec(small_spec, beta=0.2))
    worker_processes.start()
    wait_for(lambda: records.get_progress(redis, record.id).get(0, {}).get("move", 0) > 5)
    assert graph.cancel_calibration(redis, record.id)
    chain = Job.fetch(keys.chain_job_id(record.id, 0), connection=redis, serializer=JSONSerializer)
    wait_for(lambda: chain.get_status() in (JobStatus.STOPPED, JobStatus.FINISHED), 10)
    progress = records.get_progress(redis, record.id)[0]
    assert progress["move"] < progress["moves"]
    assert records.get_calibration(redis, record.id).status == CalibrationStatus.CANCELED
    assert not redis.exists(keys.chain_result(record.id, 0))


def child_pids(pid: int) -> list[int]:
    """The children of a process (Linux /proc)."""
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting to be reaped counts as dead)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def test_chain_of_a_dead_worker_is_retried_and_resumes(
    redis, worker_processes, run_workers, small_spec, monkeypatch
):
    spec = slow_spec(small_spec, beta=0.5)
    record, _ = submit(redis, spec)
    worker = worker_processes.start()
    wait_for(
        lambda: (
            json.loads(redis.get(keys.chain_checkpoint(record.id, 0)) or "{}").get("move", 0) >= 100
        )
    )
    (horse,) = child_pids(worker.pid)
    os.kill(worker.pid, signal.SIGKILL)  # the worker dies; its work horse must die with it
    worker.wait()
    wait_for(lambda: not alive(horse), 5)
    checkpoint = json.loads(redis.get(keys.chain_checkpoint(record.id, 0)))
    assert set(checkpoint) >= {"move", "rng", "current", "best", "evaluations"}
    registry = StartedJobRegistry(keys.QUEUE, connection=redis, serializer=JSONSerializer)
    assert keys.chain_job_id(record.id, 0) in registry.get_job_ids(cleanup=False)
    # What RQ's maintenance does once the dead worker's heartbeat has expired:
    registry.cleanup(timestamp=time.time() + 3600)
    # Count the cost evaluations the retried chain really makes (two-stage chains evaluate
    # static equilibria).
    evaluations = []
    real_run_chain = chain_jobs.run_chain

    def counting_run_chain(problem, reference, chain, **kw):
        calls = [0]
        real_call = StaticCost.__call__

        def counted(self, *a, **k):
            calls[0] += 1
            return real_call(self, *a, **k)

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(StaticCost, "__call__", counted)
            result = real_run_chain(problem, reference, chain, **kw)
        evaluations.append(calls[0])
        return result

    monkeypatch.setattr(chain_jobs, "run_chain", counting_run_chain)
    run_workers()
    done = records.get_calibration(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    expected = calibrate(fpm.load_problem(spec))
    # The resumed chain makes the same moves (same draws, same evaluation count), but its
    # static solves start warm from a different history after the restart, so costs agree to
    # the solver's tolerance (about 1e-7 of the force), not bit for bit: k and d to 1e-6.
    assert (done.result["k"], done.result["d"]) == pytest.approx(
        (expected.parameters.k, expected.parameters.d), rel=1e-6
    )
    # Resumed, not restarted: only the evaluations after the checkpoint were made again. (The
    # chain's count is exact; the polish's may differ by one, its stopping test seeing costs
    # that agree only to the solver's tolerance.)
    (chain,) = done.result["chains"]
    total = chain["evaluations"]
    assert total == expected.run.chains[0].evaluations
    assert evaluations == [total - checkpoint["evaluations"]] and evaluations[0] < total
    # Exactly one parameter set, and no checkpoint left behind.
    assert redis.zcard(keys.parameter_sets()) == 1
    assert not redis.exists(keys.chain_checkpoint(record.id, 0))


def test_hashes_ignore_spelt_out_defaults(small_spec):
    plain = dump_spec(fpm.load_problem(small_spec).spec)
    small_spec["fpm"]["dt"] = 1e-3  # the default, spelt out
    assert spec_hash(dump_spec(fpm.load_problem(small_spec).spec)) == spec_hash(plain)
    small_spec["annealing"]["seed"] = 99
    changed = dump_spec(fpm.load_problem(small_spec).spec)
    assert spec_hash(changed) != spec_hash(plain) and fem_hash(changed) == fem_hash(plain)


def test_newer_fem_numerics_make_a_new_reference(small_spec, monkeypatch):
    """A stored reference is kept without expiry: after a change to the FEM numerics (a new
    FEM_VERSION) the same spec must name a different reference."""
    import store.hashing

    plain = dump_spec(fpm.load_problem(small_spec).spec)
    before = fem_hash(plain)
    monkeypatch.setattr(store.hashing, "FEM_VERSION", "newer")
    assert fem_hash(plain) != before


def test_every_job_name_is_a_function_rq_can_import():
    import importlib

    names = (keys.FEM_JOB, keys.BASIS_JOB, keys.CHAIN_JOB, keys.DAMPING_JOB, keys.FINALIZE_JOB)
    for name in (*names, keys.FAILURE_CALLBACK, keys.PROFILE_JOB):
        module, function = name.rsplit(".", 1)
        assert callable(getattr(importlib.import_module(module), function)), name


def _priority_after_lowering(environment: dict[str, str], out: Any) -> None:
    """In a child process: lower_priority() under ``environment``; put (scheduling policy,
    niceness gained)."""
    from worker.__main__ import lower_priority

    os.environ.update(environment)
    before = os.nice(0)
    lower_priority()
    out.put((os.sched_getscheduler(0), os.nice(0) - before))


@pytest.mark.parametrize(
    ("environment", "policy", "gained"),
    [({}, os.SCHED_IDLE, 0), ({"FPM_WORKER_PRIORITY": "idle"}, os.SCHED_IDLE, 0),
     ({"FPM_WORKER_PRIORITY": "3"}, os.SCHED_OTHER, 3),
     ({"FPM_WORKER_PRIORITY": "0"}, os.SCHED_OTHER, 0),
     ({"FPM_WORKER_PRIORITY": "high"}, os.SCHED_OTHER, 0)],
)  # fmt: skip
def test_work_horses_take_the_cpu_the_api_leaves(environment, policy, gained):
    """A job is all computation: its horse runs under SCHED_IDLE by default, or at a niceness
    FPM_WORKER_PRIORITY gives; a value it cannot read changes nothing."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    out = context.Queue()
    child = context.Process(target=_priority_after_lowering, args=(environment, out))
    child.start()
    child.join(30)
    assert out.get(timeout=5) == (policy, gained)
