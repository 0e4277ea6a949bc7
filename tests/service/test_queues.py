"""The fair queues, jobs RQ leaves ready, and what health counts as failed."""

from __future__ import annotations

import copy

import pytest
from rq import SimpleWorker
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer

from fpm import ProblemSpec
from service.limits import dump_spec
from store import graph, keys, records
from store.graph import JobOptions
from store.status import CalibrationStatus
from worker.__main__ import FpmSimpleWorker

pytestmark = pytest.mark.redis


def add_failed_jobs(redis, stopped: int, failed: int) -> None:
    """Jobs in the failed registry of the queue ``fpm``: ``stopped`` as RQ files a job stopped
    on request (a cancel), ``failed`` real failures."""
    q = graph.queue(redis)
    for status in [JobStatus.STOPPED] * stopped + [JobStatus.FAILED] * failed:
        job = Job.create(keys.FEM_JOB, args=("x",), connection=redis, serializer=JSONSerializer)
        job.save()
        job.set_status(status)
        q.failed_job_registry.add(job, ttl=3600)


def test_a_job_stopped_by_a_cancel_is_not_a_failure(api, redis):
    """RQ files a job stopped on request (a cancel) in the failed registry, status stopped:
    health counted one cancel as failures ("failed_jobs": 2)."""
    add_failed_jobs(redis, stopped=2, failed=1)
    assert api.get("/v1/health").json()["failed_jobs"] == 1


def test_a_finished_calibration_does_not_wait_behind_another_ones_chains(redis, small_spec):
    """The damping stage and finalize go to the priority queue, which workers drain first.

    On the one queue they would go to its end when their chains finished: behind every chain
    enqueued meanwhile (a finalize was seen to wait 2.5 minutes so, "302 of 302").
    """
    options = JobOptions(retries=0)
    first, _ = graph.submit_calibration(redis, dump_spec(ProblemSpec(**small_spec)), options)
    busy = copy.deepcopy(small_spec)
    busy["name"] = "busy"
    busy["material"]["youngs_modulus"] = 2e4  # a FEM job of its own
    busy["annealing"]["chains"] = 4
    second, _ = graph.submit_calibration(redis, dump_spec(ProblemSpec(**busy)), options)
    ran: list[str] = []

    class Recording(SimpleWorker):
        def perform_job(self, job, *args, **kwargs):  # type: ignore[no-untyped-def]
            ran.append(job.id)
            return super().perform_job(job, *args, **kwargs)

    while records.get_calibration(redis, first.id).status != CalibrationStatus.SUCCEEDED:
        assert len(ran) < 20, ran
        worker = Recording(list(keys.QUEUES), connection=redis, serializer=JSONSerializer)
        assert worker.work(burst=True, max_jobs=1, logging_level="WARNING")
    # The queue held both FEM jobs, then the first's chains, then the second's four: the
    # first's damping and finalize jumped them.
    assert ran[-2:] == [keys.damping_job_id(first.id), keys.finalize_job_id(first.id)]
    waiting = sorted(graph.queue(redis).get_job_ids())  # (RQ wakes dependents in set order)
    assert waiting == [keys.chain_job_id(second.id, c) for c in range(4)]
    assert not records.get_calibration(redis, second.id).status.terminal
    SimpleWorker(list(keys.QUEUES), connection=redis, serializer=JSONSerializer).work(
        burst=True, logging_level="WARNING"
    )
    assert records.get_calibration(redis, second.id).status == CalibrationStatus.SUCCEEDED


def test_a_job_rq_left_ready_is_queued_after_the_next_job(redis, small_spec):
    """RQ 3 moves a job whose dependencies finished onto its queue in a transaction that
    another worker's write makes it give up ("changed while enqueueing; skipping for now"),
    leaving the job for a maintenance that an idle worker runs every 405 s: in the service
    bench a damping job waited 7 minutes so. Our workers sweep the ready registries after
    every job."""
    record, _ = graph.submit_calibration(redis, dump_spec(ProblemSpec(**small_spec)), JobOptions())
    finish = graph.priority_queue(redis)
    damping = Job.fetch(keys.damping_job_id(record.id), connection=redis, serializer=JSONSerializer)

    class Raced(FpmSimpleWorker):
        def perform_job(self, job, *args, **kwargs):  # type: ignore[no-untyped-def]
            done = super().perform_job(job, *args, **kwargs)
            with redis.pipeline() as pipe:  # what RQ leaves behind: ready, not on the queue
                pipe.multi()
                finish.ready_job_registry.register_jobs([damping], pipeline=pipe)
                pipe.execute()
            return done

    worker = Raced(list(keys.QUEUES), connection=redis, serializer=JSONSerializer)
    worker.work(burst=True, max_jobs=1, logging_level="WARNING")  # the FEM job, then the sweep
    assert finish.get_job_ids() == [damping.id]
    assert finish.ready_job_registry.get_job_count(cleanup=False) == 0
