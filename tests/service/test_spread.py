"""The damping stage's load cases spread over workers (worker.spread): the
same parameters to the bit with 1, 2 and 3 real worker processes and after the worker running
a load case was killed; the timeline and critical path in the result; the per-case runs and
the replayed verdict equal to the lockstep runs."""

from __future__ import annotations

import copy
import json
import re
import signal
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rq import Worker
from rq.job import Job
from rq.registry import StartedJobRegistry
from rq.serializers import JSONSerializer

import fpm
from fpm.dynamics.voigt import SETTLED
from fpm.fitting.calibration import calibrate
from fpm.fitting.damping.choice import DampingPlan
from fpm.fitting.damping.lockstep import CaseRun, Request, Verdict, _Runs, lockstep_cpu
from fpm.fitting.damping.settings import DEFAULT
from fpm.model.stiffness import model_stiffness
from service.limits import dump_spec
from store import graph, keys, records, scratch
from store.status import CalibrationStatus
from store.timeline import critical_path, numbered
from worker.idle import local_threads
from worker.spread import CaseSpread
from worker.tasks import VALIDATION_SPAN, task_digest, to_stored

CHUNK, CONFIRM, CONFIRM_PRUNE = DEFAULT.chunk, DEFAULT.confirm, DEFAULT.confirm_prune

SMALL = json.loads(
    (Path(__file__).resolve().parents[2] / "examples" / "small-box.json").read_text()
)

FITTED = ("k", "stiffness", "volume_stiffness", "d", "d_min", "d_predicted", "depth", "dt",
          "settle_steps", "cost", "static_cost", "relative_discrepancy", "damping_runs",
          "evaluations", "validation_relative_discrepancy")  # fmt: skip


def long_cases(spec: dict[str, Any]) -> dict[str, Any]:
    """The small box with load-case runs of a second or so (dt 2e-6 s: ~500x the steps), and a
    validation case (the damping job hands it to an idle worker)."""
    spec = copy.deepcopy(spec)
    spec["fpm"].update(dt=2e-6, max_steps=1_000_000)
    spec["validation_cases"] = [
        {"name": "sideways", "forces": [{"node": 63, "vector": [0.01, 0, 0]}]}
    ]
    return spec


VALIDATION_CASES = 400
"""Validation cases that make the small box's validation task last about a second."""


def many_validation_cases(spec: dict[str, Any]) -> dict[str, Any]:
    """``spec`` with VALIDATION_CASES sideways pushes at node 63, each in its own direction
    in the xy plane."""
    spec = copy.deepcopy(spec)
    angles = np.linspace(0, 2 * np.pi, VALIDATION_CASES, endpoint=False)
    spec["validation_cases"] = [
        {"name": f"push {i}", "forces": [{"node": 63, "vector": [0.01 * c, 0.01 * s, 0]}]}
        for i, (c, s) in enumerate(zip(np.cos(angles), np.sin(angles), strict=True))
    ]
    return spec


def test_critical_path_is_the_longest_chain_of_waits():
    spans = [
        {"name": "fem", "start": 0, "end": 2, "after": []},
        {"name": "chain 0", "start": 2, "end": 10, "after": ["fem"]},
        {"name": "chain 1", "start": 2, "end": 5, "after": ["fem"]},
        {"name": "damping", "start": 10, "end": 11, "after": ["chain 0", "chain 1"]},
        {"name": "case 0", "start": 11, "end": 14, "after": ["damping"]},
        {"name": "case 1", "start": 12, "end": 20, "after": ["damping"]},  # queued 1 s
        {"name": "gather", "start": 20, "end": 21, "after": ["case 0", "case 1", "gone"]},
    ]
    seconds, path = critical_path(spans)
    assert path == ["fem", "chain 0", "damping", "case 1", "gather"]
    assert seconds == 2 + 8 + 1 + 8 + 1  # durations only: the queueing second is left out
    assert critical_path([]) == (0.0, [])


def test_distinct_tasks_named_alike_are_numbered_and_a_task_run_twice_is_not():
    spans = [
        {"name": "damping", "task": None},
        {"name": "damping: d 0.1, all load cases", "task": "a"},
        {"name": "damping: d 0.1, all load cases", "task": "b"},  # other caps, say
        {"name": "damping: d 0.1, all load cases", "task": "a"},  # run again
        {"name": "damping: d 0.1, all load cases", "task": "c"},
        {"name": "finalize"},
    ]
    names = [s["name"] for s in numbered(spans)]
    d = "damping: d 0.1, all load cases"
    assert names == ["damping", d, f"{d} [2]", d, f"{d} [3]", "finalize"]


@pytest.mark.parametrize("cap", [1_000_000, 3 * CHUNK, 3 * CHUNK + 50])
def test_separate_runs_equal_the_lockstep_runs(cap):
    """The predicted d's runs, each case on its own, and the verdict replayed from them equal
    the lockstep runs: settled (the answer to the bit), and stopped by the cap (failed when the
    cap is on a milestone, done but unsettled between two, as the lockstep decides)."""
    problem = fpm.load_problem(long_cases(SMALL))
    stiffness = model_stiffness(problem, [22.4347])
    runs = _Runs(problem, stiffness, None, 2e-6)
    try:
        caps = [cap] * runs.cases
        lockstep, verdict = runs(0.11, caps, None, to_cap=True)
        separate, replayed = runs.separate(0.11, caps)
    finally:
        runs.close()
    assert replayed.outcome == verdict.outcome
    assert [r.state for r in separate] == [r.state for r in lockstep]
    assert [r.steps for r in separate] == [r.steps for r in lockstep]
    if cap == 1_000_000:
        assert verdict.outcome == "done" and all(r.steps > 10 * CHUNK for r in separate)
        for one, other in zip(separate, lockstep, strict=True):
            assert np.array_equal(one.displacements, other.result().displacements)
    else:
        assert verdict.outcome == ("failed" if cap % CHUNK == 0 else "done")


@pytest.fixture
def predicted_runs():
    """The lockstep runs of the long small box at (k 22.4347, d = 0.11, no budget, to a cap of
    10^6 steps): (the _Runs, its cases' runs at d, as the predicted d's beside which others
    run)."""
    problem = fpm.load_problem(long_cases(SMALL))
    runs = _Runs(problem, model_stiffness(problem, [22.4347]), None, 2e-6)
    try:
        predicted, _ = runs(0.11, [1_000_000] * runs.cases, None, to_cap=True)
        yield runs, predicted
    finally:
        runs.close()


@pytest.mark.parametrize("named_after", [0.0, 0.7])
@pytest.mark.parametrize("short", [False, True])
def test_caps_named_later_give_the_verdict_of_the_caps_known(named_after, short, predicted_runs):
    """A margin probe run beside the predicted d's learns its caps (twice their steps) only
    once they have ended: its cases run on meanwhile, and a case that went past its cap is
    taken as it stood there, so the verdict is the one of the probe with its caps known: it
    settles within twice the steps, and fails with caps shorter than the first prediction
    (the cases reach them unsettled)."""
    runs, predicted = predicted_runs
    wide = [1_000_000] * runs.cases
    caps = [2 * CHUNK if short else 2 * r.steps for r in predicted]
    d = 0.11 / 1.12
    _, verdict = runs(d, caps, None, estimate=True)
    start = time.monotonic()

    def resolve():
        return {"caps": caps} if time.monotonic() - start >= named_after else None

    request = Request(d, tuple(wide), None, estimate=True, caps_later=True)
    later, late = runs.locked(request, resolve)
    assert (late.outcome, late.total, late.predicted) == (
        verdict.outcome, verdict.total, verdict.predicted
    )  # fmt: skip
    assert verdict.outcome == ("failed" if short else "settles")
    assert all(r.steps <= c for r, c in zip(later, caps, strict=True))  # as capped
    if short:
        assert [(r.steps, r.finished) for r in later] == [(c, False) for c in caps]
    _, how = runs.locked(request, lambda: {"caps": None})  # the search asks none
    assert how.outcome == "dropped"


def test_a_lockstep_counts_the_cpu_its_pool_threads_spent(predicted_runs):
    """A request run on the damping job's thread runs its pieces on the pool's threads: the
    thread's own CPU seconds and those it is credited with (lockstep_cpu) are together the
    process's, so the request's span neither loses them nor the damping job's counts them
    twice."""
    runs, predicted = predicted_runs
    request = Request(0.11 / CONFIRM, tuple(r.steps for r in predicted), None, to_cap=True)
    process, own, pooled = time.process_time(), time.thread_time(), lockstep_cpu()
    runs.locked(request)
    process = time.process_time() - process
    own, pooled = time.thread_time() - own, lockstep_cpu() - pooled
    assert pooled > 0 and own > 0  # the pieces ran on the pool, this thread decided
    assert 0.9 * process <= own + pooled <= process + 1e-3, (process, own, pooled)


def submit(redis, spec):
    dumped = dump_spec(fpm.load_problem(spec).spec)
    return graph.submit_calibration(redis, dumped, graph.JobOptions(retries=1))


def wait_done(redis, calibration_id: str, timeout: float = 240.0) -> records.CalibrationRecord:
    deadline = time.monotonic() + timeout
    while True:
        record = records.get_calibration(redis, calibration_id)
        assert record is not None
        if record.status.terminal:
            return record
        assert time.monotonic() < deadline, f"timed out in {record.phase}"
        time.sleep(0.1)


def start_workers(redis, worker_processes, n: int) -> list[Any]:
    started = [worker_processes.start() for _ in range(n)]
    deadline = time.monotonic() + 60
    while len(Worker.all(connection=redis)) < n:
        assert time.monotonic() < deadline, "workers did not register"
        time.sleep(0.1)
    return started


def case_spans(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The spans of the predicted d's load cases, each run on its own."""
    return [s for s in result["jobs"] if re.match(r"damping: d .*, load case \d$", s["name"])]


def ahead_spans(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The spans of the d run ahead (the margin's probes; a confirming d where the reduced steps
    cannot rule it out)."""
    return [s for s in result["jobs"] if s["name"].endswith(", all load cases")]


@pytest.mark.redis
def test_the_damping_job_leaves_the_cores_of_the_busy_workers_on_its_host(redis):
    def register(name: str, host: str | None = None) -> Worker:
        worker = Worker(["elsewhere"], connection=redis, name=name)
        worker.hostname = host or worker.hostname
        worker.register_birth()
        worker.set_state("idle")
        return worker

    register("me")
    here = [register(f"here {i}") for i in range(3)]
    away = register("away", host="another-host")
    assert local_threads(redis, "me", 2) == 2  # every other worker idle
    assert local_threads(redis, "me", 2, queued=1) == 1  # a task an idle worker will take
    away.set_state("busy")
    assert local_threads(redis, "me", 2) == 2  # a busy worker on another host
    here[0].set_state("busy")
    assert local_threads(redis, "me", 2) == 1
    assert local_threads(redis, "me", 4) == 3
    assert local_threads(redis, "me", 4, queued=5) == 1  # two idle workers take two of them
    for worker in here[1:]:
        worker.set_state("busy")
    assert local_threads(redis, "me", 2) == 1  # at least one: its own
    assert local_threads(redis, "me", 4) == 1
    here[0].set_state("idle")
    assert local_threads(redis, "me", 4) == 2


@pytest.mark.redis
def test_a_request_waiting_for_its_name_starts_once_the_cases_are_claimed(redis):
    """One core here: load case 0 held by another worker (its run stored after 1 s), case 1
    and a request named once both cases have run. The request starts here as soon as case 1
    has run, not once case 0 has (the damping job had sat idle that long); it is named once
    both are stored."""
    plan = DampingPlan([1.0], 2, 1e-3)
    spread = CaseSpread(redis, "calibration", plan, "me", 60, lambda: None)
    spread.threads = 1
    specs = [{**asdict(plan), "d": 0.1, "load_case": j, "cap": 100, "after": "damping"}
             for j in (0, 1)]  # fmt: skip
    named_later = {"d": 0.2, "budget": None, "caps_later": True}
    specs.append({**asdict(plan), "request": named_later, "after": "damping"})
    tasks = [task_digest(spec) for spec in specs]
    assert scratch.claim_case(redis, "calibration", tasks[0], "another worker")
    run = CaseRun(
        steps=10, state=SETTLED, settle_force=1.0, history=[], displacements=np.zeros((2, 3))
    )
    stored_at: list[float] = []

    def other_worker() -> None:
        time.sleep(1.0)
        stored_at.append(time.monotonic())
        scratch.save_case_run(redis, "calibration", tasks[0], *to_stored([run], None))

    started: dict[str, float] = {}

    def named() -> bool:
        if not all(scratch.has_case_run(redis, "calibration", t) for t in tasks[:2]):
            return False
        started["named"] = time.monotonic()
        return True

    def request() -> tuple[list[CaseRun], Verdict]:
        started["request"] = time.monotonic()
        while "named" not in started:  # as a request waits for its name
            time.sleep(0.05)
        return [], Verdict("lost", 20.0)

    thread = threading.Thread(target=other_worker)
    thread.start()
    done = spread._round(
        specs, [lambda: pytest.fail("case 0 is the other's"), lambda: ([run], None), request],
        0, (named, {2}),
    )  # fmt: skip
    thread.join()
    assert started["request"] < stored_at[0] < started["named"]
    assert [len(runs) for runs, _ in done] == [1, 1, 0] and done[2][1] == Verdict("lost", 20.0)


@pytest.mark.redis
def test_same_parameters_with_one_two_and_three_workers(redis, worker_processes):
    spec = long_cases(SMALL)
    results, workers_of_cases, ahead, validated_apart = {}, {}, {}, {}
    for n in (1, 2, 3):
        redis.flushdb()
        started = start_workers(redis, worker_processes, n)
        record, _ = submit(redis, spec)
        done = wait_done(redis, record.id)
        assert done.status == CalibrationStatus.SUCCEEDED, done.error
        results[n] = {name: done.result[name] for name in FITTED}
        cases = case_spans(done.result)
        assert sorted(s["name"][-1] for s in cases) == ["0", "1"]  # one run per load case
        workers_of_cases[n] = {s["worker"] for s in cases}
        ahead[n] = len(ahead_spans(done.result))
        worker_of = {s["name"]: s["worker"] for s in done.result["jobs"]}
        validated_apart[n] = worker_of[VALIDATION_SPAN] != worker_of["damping"]
        names = [s["name"] for s in done.result["jobs"]]
        assert names[0] == "FEM reference" and names[-1] == "finalize"
        assert {"chain 0", "chain 1", "damping", "damping (gather)"} <= set(names)
        damping = next(s for s in done.result["jobs"] if s["name"] == "damping")
        phases = [p["phase"] for p in damping["phases"]]  # what it did alone, before hand-out
        assert phases[0] == "load" and "polish" in phases and phases[-1] == "damping"
        alone = sum(p["seconds"] for p in damping["phases"])
        assert alone == pytest.approx(damping["end"] - damping["start"], abs=1e-6)
        tasks = [s["task"] for s in done.result["jobs"] if s.get("task") is not None]
        assert len(set(tasks)) == len(tasks)  # each task ran once
        assert len(set(names)) == len(names)  # and each span has a name of its own
        for s in done.result["jobs"]:
            assert s["start"] <= s["end"] and s["cpu"] >= 0 and s["worker"] != "?"
        seconds, path = critical_path(done.result["jobs"])
        assert done.result["critical_path"] == path and path[-1] == "finalize"
        assert done.result["critical_path_seconds"] == pytest.approx(seconds)
        wall = max(s["end"] for s in done.result["jobs"]) - done.result["jobs"][0]["start"]
        assert 0 < seconds <= wall
        for process in started:
            worker_processes.stop(process)
    assert results[1] == results[2] == results[3]  # to the bit (JSON floats round-trip)
    expected = calibrate(fpm.load_problem(spec)).to_dict()  # in-process, one thread pool
    assert results[1] == {name: expected[name] for name in FITTED}
    assert len(workers_of_cases[1]) == 1 and ahead[1] == 0  # nothing run ahead on one worker
    assert ahead[2] >= 1 and ahead[3] >= 1  # a d run ahead at once (the margin's edge)
    assert len(workers_of_cases[3]) >= 2, workers_of_cases  # the other workers took cases
    assert not validated_apart[1] and (validated_apart[2] or validated_apart[3])


@pytest.mark.redis
@pytest.mark.parametrize(
    ("task", "workers"),
    [
        (r"load case \d$", 2),
        (r"all load cases$", 2),
        (r"validation cases$", 3),
    ],
)
def test_worker_killed_holding_a_task_of_the_damping_stage_loses_nothing(
    redis, worker_processes, task, workers
):
    """A load case at one d, a d run ahead (a request: the margin's probe or a confirming d),
    the validation cases: the worker that
    holds one is killed mid-run, its task runs again elsewhere, the parameters are those of
    the calibration in-process. (One validation case of the small box takes a few ms, so that
    the kill lands while its task runs, not after it ended or between its stored answer and
    its span, it is given VALIDATION_CASES of them: about a second.)"""
    spec = long_cases(SMALL)
    if "validation" in task:
        spec = many_validation_cases(spec)
    started = start_workers(redis, worker_processes, workers)
    record, _ = submit(redis, spec)
    registry = StartedJobRegistry(keys.PRIORITY_QUEUE, connection=redis, serializer=JSONSerializer)
    prefix = f"{record.id}-case-"
    deadline = time.monotonic() + 120

    def holding() -> Worker | None:
        """The worker holding a started job of ``task`` now (None: none is, or it has just
        ended: a request the search drops ends early)."""
        for job_id in registry.get_job_ids(cleanup=False):
            job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
            if job_id.startswith(prefix) and re.search(task, job.description or ""):
                for w in Worker.all(connection=redis):
                    if w.get_current_job_id() == job_id:
                        return w
        return None

    while (holder := holding()) is None:
        assert time.monotonic() < deadline, f"no {task} job started on another worker"
        time.sleep(0.02)
    (victim,) = [p for p in started if p.pid == holder.pid]
    worker_processes.stop(victim, signal.SIGKILL)  # the worker and its work horse, mid-run
    done = wait_done(redis, record.id)
    assert done.status == CalibrationStatus.SUCCEEDED, done.error
    expected = calibrate(fpm.load_problem(spec)).to_dict()
    assert {name: done.result[name] for name in FITTED} == {name: expected[name] for name in FITTED}
    spans = [s for s in done.result["jobs"] if re.search(task, s["name"])]
    assert spans and holder.name not in {s["worker"] for s in spans}  # run again elsewhere
