"""Build and cancel a calibration's job graph; used by the service (imports no numerics).

A calibration is::

    fem job (skipped if stored) --+--> chain 0 .. chain n-1 --> damping --> finalize
    reduced-basis job ------------/

(the damping job only for the two-stage method: polish, depth, fastest-settling d; the
reduced-basis job only for its families+volume chains, :func:`builds_basis`: it needs no FEM
reference, so it runs beside the FEM job). The chains and a large problem's FEM and
reduced-basis jobs go to the queue of long jobs; the damping job, finalize and a small
problem's (:data:`SMALL_FEM_NODES`) FEM and reduced-basis jobs to the priority queue that
workers drain first (:data:`store.keys.QUEUES`).

Jobs are enqueued by dotted path with RQ's JSON serializer and carry only ids; the spec, the
FEM reference and the chain results live under our own keys (:mod:`store.keys`). Chains
depend on the FEM and reduced-basis jobs and finalize on the chains with ``allow_failure``: a
failed dependency still wakes the next job, which then records the calibration as failed (no
job is left waiting for ever).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from redis import Redis
from rq import Callback, Queue, Retry
from rq.command import send_stop_job_command
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Dependency, Job, JobStatus
from rq.serializers import JSONSerializer

from fpm.model.spec import VOLUME_MODES

from . import keys, records, scratch
from .hashing import export_hash, fem_hash, fem_spec, spec_hash, view_hash
from .status import CalibrationStatus, FemStatus
from .text import escape

PENDING = (JobStatus.QUEUED, JobStatus.DEFERRED, JobStatus.SCHEDULED, JobStatus.STARTED)


@dataclass(frozen=True)
class JobOptions:
    """Limits of the jobs a calibration enqueues.

    Attributes:
        fem_timeout, chain_timeout, finalize_timeout: wall time a job may run, s (the damping
            stage, which runs dynamic simulations like a paper-method chain, gets
            chain_timeout).
        retries: times a job is re-run after its worker died (or it raised).
        result_ttl: how long RQ keeps a finished job's return value, s (our records stay).
        failure_ttl: how long RQ keeps a failed job, s.
    """

    fem_timeout: int = 1800
    chain_timeout: int = 6 * 3600
    finalize_timeout: int = 1800
    retries: int = 2
    result_ttl: int = 24 * 3600
    failure_ttl: int = 7 * 24 * 3600


def queue(redis: Redis) -> Queue:
    """The project's queue of long jobs (FEM, chains) with the JSON serializer."""
    return Queue(keys.QUEUE, connection=redis, serializer=JSONSerializer)


def priority_queue(redis: Redis) -> Queue:
    """The queue of the jobs that finish a calibration (damping stage, finalize), which
    workers drain first (:data:`store.keys.PRIORITY_QUEUE`)."""
    return Queue(keys.PRIORITY_QUEUE, connection=redis, serializer=JSONSerializer)


def queues(redis: Redis) -> list[Queue]:
    """Every queue, in the order workers take jobs from them (:data:`store.keys.QUEUES`)."""
    return [Queue(name, connection=redis, serializer=JSONSerializer) for name in keys.QUEUES]


READY_SWEEPS = 5
"""Attempts per queue of :func:`enqueue_ready` (each gives up a job another worker touched)."""


def enqueue_ready(redis: Redis) -> int:
    """Move onto their queues the jobs whose dependencies have finished but which RQ left in its
    ready registry; returns how many.

    RQ 3 marks such a job ready, then moves it onto its queue in a WATCH transaction that
    watches the whole ready registry: when another worker touches the registry meanwhile, the
    job stays there "for now", until a worker's maintenance, which an idle worker runs only
    when its blocking dequeue times out (405 s). Two workers finishing jobs at once did this:
    a damping job waited 7 minutes with both workers idle. Workers call this after every job.
    """
    moved = 0
    for q in queues(redis):
        registry = q.ready_job_registry
        for _ in range(READY_SWEEPS):
            if not registry.get_job_count(cleanup=False):
                break
            moved += len(registry.cleanup())
    return moved


def answered_by(redis: Redis, spec: dict[str, Any]) -> str | None:
    """The id of the calibration an identical ``spec`` would be answered with (queued, running
    or succeeded), or None when submitting it starts a new one."""
    existing_id = redis.get(keys.calibration_by_spec(spec_hash(spec)))
    if existing_id is None:
        return None
    raw = existing_id.decode() if isinstance(existing_id, bytes) else str(existing_id)
    existing = records.get_calibration(redis, raw)
    if existing is not None and existing.status in (
        CalibrationStatus.QUEUED,
        CalibrationStatus.RUNNING,
        CalibrationStatus.SUCCEEDED,
    ):
        return existing.id
    return None


def submit_calibration(
    redis: Redis,
    spec: dict[str, Any],
    options: JobOptions,
    supplied: dict[str, Any] | None = None,
) -> tuple[records.CalibrationRecord, bool]:
    """Start a calibration of the validated ``spec`` (a dumped ProblemSpec); ``supplied``:
    the reference of a spec with ``reference.displacements`` (:func:`submit_fem`).

    Returns (record, created): an identical spec already queued, running or succeeded gives
    that calibration and ``created=False``; otherwise a new record and its jobs.
    """
    digest = spec_hash(spec)
    by_spec = keys.calibration_by_spec(digest)
    record = records.CalibrationRecord(
        id=keys.new_calibration_id(),
        spec=spec,
        spec_hash=digest,
        fem_hash=fem_hash(spec),
        chains=spec["annealing"]["chains"],
        name=spec["name"],
        fem_cached=bool(redis.exists(keys.fem_reference(fem_hash(spec)))),
    )

    def claim(pipe: Any) -> records.CalibrationRecord | None:
        existing_id = pipe.get(by_spec)
        if existing_id is not None:
            existing = records.get_calibration(pipe, existing_id.decode())
            if existing is not None and existing.status in (
                CalibrationStatus.QUEUED,
                CalibrationStatus.RUNNING,
                CalibrationStatus.SUCCEEDED,
            ):
                pipe.unwatch()
                return existing
        pipe.multi()
        records.write_calibration(pipe, record)
        return None

    transaction: Any = redis.transaction  # its stub wants a callable returning None
    existing: records.CalibrationRecord | None = transaction(
        claim, by_spec, value_from_callable=True
    )
    if existing is not None:
        return existing, False
    _enqueue(redis, record, options, supplied)
    return record, True


def _enqueue(
    redis: Redis,
    record: records.CalibrationRecord,
    options: JobOptions,
    supplied: dict[str, Any] | None = None,
) -> None:
    """Enqueue the jobs: chains on the queue of long jobs, the damping stage and finalize on
    the priority queue (RQ puts a job whose dependencies finished on its own queue, so they
    jump the chains of calibrations submitted later)."""
    q = queue(redis)
    finish = priority_queue(redis)
    common = _common(options)
    fem_job = None if record.fem_cached else submit_fem(redis, record.spec, options, supplied)
    basis_job = _enqueue_basis(redis, record, options) if builds_basis(record.spec) else None
    before = [j for j in (fem_job, basis_job) if j is not None]
    chains = [
        q.enqueue_call(
            keys.CHAIN_JOB,
            args=(record.id, chain),
            job_id=keys.chain_job_id(record.id, chain),
            timeout=options.chain_timeout,
            depends_on=Dependency(before, allow_failure=True) if before else None,
            description=f"{escape(record.name)}: chain {chain}",
            **common,
        )
        for chain in range(record.chains)
    ]
    before_finalize = chains
    if record.spec["annealing"]["method"] == "two-stage":
        before_finalize = [
            finish.enqueue_call(
                keys.DAMPING_JOB,
                args=(record.id,),
                job_id=keys.damping_job_id(record.id),
                timeout=options.chain_timeout,
                depends_on=Dependency(chains, allow_failure=True),
                description=f"{escape(record.name)}: damping",
                **common,
            )
        ]
    finish.enqueue_call(
        keys.FINALIZE_JOB,
        args=(record.id,),
        job_id=keys.finalize_job_id(record.id),
        timeout=options.finalize_timeout,
        depends_on=Dependency(before_finalize, allow_failure=True),
        description=f"{escape(record.name)}: finalize",
        **common,
    )


def builds_basis(spec: dict[str, Any]) -> bool:
    """The calibration of ``spec`` has a reduced-basis job: two-stage with a stiffness mode
    whose chains anneal stage 1's reduced linear model (families+volume, field)."""
    return spec["annealing"]["method"] == "two-stage" and spec["fpm"]["stiffness"] in VOLUME_MODES


def _enqueue_basis(redis: Redis, record: records.CalibrationRecord, options: JobOptions) -> Job:
    """The reduced-basis job (no dependency: it needs the spec only), on the queue its FEM job
    would take (:func:`submit_fem`): about as long as the FEM's solve."""
    small = fem_nodes(record.spec) <= SMALL_FEM_NODES
    return (priority_queue(redis) if small else queue(redis)).enqueue_call(
        keys.BASIS_JOB,
        args=(record.id,),
        job_id=keys.basis_job_id(record.id),
        timeout=options.chain_timeout,
        description=f"{escape(record.name)}: reduced basis",
        **_common(options),
    )


def submit_fem(
    redis: Redis,
    spec: dict[str, Any],
    options: JobOptions,
    supplied: dict[str, Any] | None = None,
) -> Job | None:
    """Make sure the FEM reference of ``spec`` is stored or on its way.

    A spec with ``reference.displacements`` has no FEM job: ``supplied`` (the stored
    FemResult layout of those displacements) is stored as its reference at once.

    Returns the pending FEM job to wait for (an existing one if the same reference is already
    being computed), or None if the reference is stored.
    """
    digest = fem_hash(spec)
    if redis.exists(keys.fem_reference(digest)):
        return None
    if (spec.get("reference") or {}).get("displacements") is not None:
        if supplied is None:
            raise ValueError("a spec with reference.displacements needs its supplied reference")
        store_supplied_reference(redis, spec, supplied)  # the user's own reference: no FEM job
        return None
    q = queue(redis)
    job_id = keys.fem_job_id(digest)
    try:
        job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
        if job.get_status() in PENDING:
            return job
    except NoSuchJobError:
        pass
    pipe = redis.pipeline()
    pipe.hset(
        keys.fem_meta(digest),
        mapping={
            "id": digest,
            "status": FemStatus.QUEUED.value,
            "spec": json.dumps(fem_spec(spec)),
            "created": str(time.time()),
            "error": "",
        },
    )
    pipe.execute()
    if fem_nodes(spec) <= SMALL_FEM_NODES:
        q = priority_queue(redis)  # a short job: it must not wait behind another's chains
    return q.enqueue_call(
        keys.FEM_JOB,
        args=(digest,),
        job_id=job_id,
        timeout=options.fem_timeout,
        description=f"FEM reference {digest[:12]}",
        **_common(options),
    )


def store_supplied_reference(redis: Redis, spec: dict[str, Any], reference: dict[str, Any]) -> str:
    """Store a spec's supplied ``reference.displacements`` as its reference, so chains and
    finalize read it as they read a FEM reference; no FEM job runs.

    ``reference`` is the stored FemResult layout (``nodes``, ``displacements``, ``load_cases``,
    ..., model and method ``"supplied"``), built by the caller from the loaded problem (the
    store takes only the spec from the numerical core). Returns the reference id."""
    digest = fem_hash(spec)
    now = time.time()
    meta = {
        "id": digest,
        "status": FemStatus.SUCCEEDED.value,
        "spec": json.dumps(fem_spec(spec)),
        "created": str(now),
        "finished": now,
        "error": "",
        "n_nodes": len(reference["nodes"]),
        "load_cases": reference["load_cases"],
        "model": "supplied",
    }
    records.save_fem_reference(redis, digest, *records.pack_reference(reference), meta)
    return digest


SMALL_FEM_NODES = 5_000
"""A FEM reference of at most this many nodes (a direct solve of about a second) goes on the
priority queue with the jobs that finish calibrations; larger ones on the queue of long jobs."""


def fem_nodes(spec: dict[str, Any]) -> int:
    """About how many nodes the FEM of ``spec`` has, from the validated spec alone (no
    numerics loaded): a box's lattice, a mesh's nodes, a voxel grid's solid cells (a lower
    bound on its nodes), a network's nodes; a large number when the geometry is unknown."""
    geometry = spec.get("geometry", {})
    kind = geometry.get("type")
    if kind == "box":
        nx, ny, nz = geometry["nodes"]
        return int(nx * ny * nz)
    if kind == "voxels":
        return sum(bool(c) for plane in geometry["occupancy"] for row in plane for c in row)
    if kind in ("mesh", "network"):
        return len(geometry.get("nodes", ()))
    return 1 << 62


def _common(options: JobOptions) -> dict[str, Any]:
    """Options every job gets: retries, RQ's TTLs, and the failure callback.

    No queue ``ttl``: a job waiting behind a long queue must not silently expire.
    """
    return {
        "retry": Retry(max=options.retries) if options.retries else None,
        "result_ttl": options.result_ttl,
        "failure_ttl": options.failure_ttl,
        "on_failure": Callback(keys.FAILURE_CALLBACK),
    }


def _fetch(redis: Redis, job_id: str) -> tuple[Job | None, JobStatus | None]:
    """The job of ``job_id`` and its status, or (None, None) when RQ has no such job."""
    try:
        job = Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
    except NoSuchJobError:
        return None, None
    return job, job.get_status()


def request_profile(redis: Redis, calibration_id: str, timeout: int) -> bool:
    """Enqueue the profile job of a succeeded calibration unless it is pending; False when its
    last run failed (the failure is stored: :func:`store.scratch.get_profile`, and RQ keeps the
    failed job for :data:`store.scratch.PROFILE_FAILED_TTL` seconds, so it is not re-run at
    every poll)."""
    job_id = keys.profile_job_id(calibration_id)
    job, job_status = _fetch(redis, job_id)
    if job_status == JobStatus.FAILED:
        return False
    if job_status not in PENDING:
        queue(redis).enqueue_call(
            keys.PROFILE_JOB,
            args=(calibration_id,),
            job_id=job_id,
            timeout=timeout,
            result_ttl=60,
            failure_ttl=scratch.PROFILE_FAILED_TTL,
            description=f"profile of calibration {calibration_id}",
        )
    return True


@dataclass(frozen=True)
class ExportState:
    """Where an export stands (:func:`request_export`).

    Attributes:
        body: the export's bytes once made, else None.
        error: why the last export job failed (the cool-down is not over), else None.
        invalid: the failure was the input's (the parameters do not fit the spec's lattice):
            the same input fails again.
        retry_after: seconds to wait before asking again (the rest of the cool-down when
            failed; the polling interval when pending).
    """

    body: bytes | None = None
    error: str | None = None
    invalid: bool = False
    retry_after: int = 1

    @property
    def pending(self) -> bool:
        return self.body is None and self.error is None


EXPORT_POLL = 1
"""Seconds a client waits before asking again for a pending export (Retry-After)."""


def request_export(
    redis: Redis, parameter_set_id: str, fmt: str, spec: dict[str, Any], timeout: int
) -> ExportState:
    """The export of a stored parameter set in ``fmt`` (``spec``: the one it was fitted on, from
    its calibration record): its bytes when cached, the failure of its last job during the
    cool-down, else pending, its job enqueued unless it already is.

    One job however many requests race: the job id derives from the export's key, and only the
    request that wins :func:`store.scratch.claim_export` (SET NX) enqueues it. The job goes on
    the priority queue for a lattice of at most :data:`SMALL_FEM_NODES` nodes (a fraction of a
    second), else on the queue of long jobs. RQ keeps a job that failed without storing why
    (its worker died, or it was killed) :data:`store.scratch.EXPORT_FAILED_TTL` seconds, which
    is then its cool-down.
    """
    digest = export_hash(parameter_set_id, fmt)
    job = _CachedJob(keys.EXPORT_JOB, keys.export_job_id(digest), (parameter_set_id, fmt), "export")
    return _request_cached(redis, digest, job, spec, timeout, f" of {parameter_set_id} as {fmt}")


def request_view(
    redis: Redis, parameter_set_id: str, spec: dict[str, Any], timeout: int
) -> ExportState:
    """The 3D view data of a stored parameter set (``worker.view``), made and cached exactly as
    an export is (:func:`request_export`; under its own :func:`store.hashing.view_hash`)."""
    digest = view_hash(parameter_set_id)
    job = _CachedJob(keys.VIEW_JOB, keys.view_job_id(digest), (parameter_set_id,), "3D view")
    return _request_cached(redis, digest, job, spec, timeout, f" of {parameter_set_id}")


@dataclass(frozen=True)
class _CachedJob:
    """The job that makes bytes cached like an export: its dotted path, id, arguments and what
    it makes (``export``, ``3D view``)."""

    function: str
    job_id: str
    args: tuple[str, ...]
    kind: str


def _request_cached(
    redis: Redis, digest: str, job: _CachedJob, spec: dict[str, Any], timeout: int, of: str
) -> ExportState:
    """:func:`request_export`'s steps for the bytes cached under ``digest``, made by ``job``
    (``of`` completes its description: " of <parameter set> ...")."""
    body = scratch.get_export(redis, digest)
    if body is not None:
        return ExportState(body=body)
    failure = scratch.get_export_failure(redis, digest)
    if failure is not None:
        data, left = failure
        return ExportState(error=data["error"], invalid=bool(data["invalid"]), retry_after=left)
    found, job_status = _fetch(redis, job.job_id)
    if job_status in PENDING:
        return ExportState(retry_after=EXPORT_POLL)
    if found is not None and job_status == JobStatus.FAILED:
        left = int(redis.ttl(found.key))
        return ExportState(
            error=f"the {job.kind} job stopped before it finished (its worker died or it ran "
            f"past its timeout of {timeout} s)",
            retry_after=max(left, 1),
        )
    if scratch.claim_export(redis, digest):
        body = scratch.get_export(redis, digest)  # made between our first look and the claim
        if body is not None:
            return ExportState(body=body)
        q = priority_queue(redis) if fem_nodes(spec) <= SMALL_FEM_NODES else queue(redis)
        q.enqueue_call(
            job.function,
            args=job.args,
            job_id=job.job_id,
            timeout=timeout,
            result_ttl=60,
            failure_ttl=scratch.EXPORT_FAILED_TTL,
            description=f"{job.kind} of parameter set{of}",
        )
    return ExportState(retry_after=EXPORT_POLL)


def cancel_calibration(redis: Redis, calibration_id: str) -> bool:
    """Mark a calibration canceled, stop its running jobs (reduced basis, chains, damping stage
    and the load-case jobs it handed out, finalize) and drop its queued ones.

    Returns False if it had already finished (nothing changed). The shared FEM job is left
    alone: another calibration may need the same reference.
    """
    changed = records.update_calibration(
        redis,
        calibration_id,
        {"status": CalibrationStatus.CANCELED, "finished": time.time()},
    )
    if not changed:
        return False
    record = records.get_calibration(redis, calibration_id)
    assert record is not None
    job_ids = [keys.basis_job_id(calibration_id)]
    job_ids += [keys.chain_job_id(calibration_id, c) for c in range(record.chains)]
    job_ids += [keys.damping_job_id(calibration_id), keys.finalize_job_id(calibration_id)]
    job_ids += [
        keys.case_job_id(calibration_id, t) for t in scratch.case_tasks(redis, calibration_id)
    ]
    for job in Job.fetch_many(job_ids, connection=redis, serializer=JSONSerializer):
        if job is None:
            continue
        status = job.get_status()
        try:
            if status == JobStatus.STARTED:
                send_stop_job_command(redis, job.id, serializer=JSONSerializer)
            elif status in PENDING:
                job.cancel()
        except (InvalidJobOperation, NoSuchJobError):
            pass  # it finished or was canceled meanwhile: the record says canceled anyway
    return True
