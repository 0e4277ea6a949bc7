"""A calibration's scratch data in Redis: what its jobs hand on to each other, kept
:data:`SCRATCH_TTL` seconds (no numerical code here).

- stage 1's first reduced basis (:class:`fpm.fitting.reduced.ReducedBasis`: a JSON layout and
  raw arrays), built once and read by every chain and the damping stage;
- chain checkpoints (:class:`fpm.fitting.annealing.Checkpoint` as JSON), so that a retried
  chain resumes;
- chain results (:class:`fpm.fitting.stiffness_stage.ChainResult` as JSON), read by the damping
  stage and finalize, and the same by the identity of their fit
  (:func:`store.hashing.stiffness_hash`), which a later calibration of that fit takes (one run
  again after its damping stage failed);
- the damping stage's result (:class:`fpm.fitting.damping.stage.DampingStage` as JSON);
- the damping stage's load-case tasks (:mod:`worker.spread`): what to run, who runs it (a
  claim its holder renews), and the run (JSON and raw float64 displacements);
- the spans of a calibration's jobs (worker, start, end, CPU s; :mod:`store.timeline`);
- progress reports, one field per chain and one for the damping stage;
- the FPM-vs-FEM profile data of a succeeded calibration (the web view's plot);
- the exports of parameter sets (bytes, by :func:`store.hashing.export_hash`; kept
  :data:`EXPORT_TTL` seconds) and the failures of export jobs.

Values are the records' ``to_dict()`` as JSON; the job runner turns them back into records.
"""

from __future__ import annotations

import gzip
import json
from typing import Any

from redis import Redis

from . import keys
from .status import CalibrationStatus

SCRATCH_TTL = 7 * 24 * 3600
"""Seconds that chain checkpoints, chain results, progress and profiles are kept (s)."""

PROFILE_FAILED_TTL = 600
"""Seconds a failed profile is remembered, so that polling does not re-run it at once (s)."""


EXPORT_TTL = 24 * 3600
"""Seconds an export is kept (s). Exports are derived data, made again from records that have no
expiry, and a large lattice's is tens of MB: kept forever they would fill a Redis that must not
evict (``noeviction``). A day serves the repeated downloads of one session (web view, SDK,
CLI) from the cache; a later one waits once more for the job."""

EXPORT_GZIP_LEVEL = 6
"""gzip level of cached exports (zlib's default: most of the gain of 9 at a fraction of
its time)."""

EXPORT_FAILED_TTL = 600
"""Seconds a failed export is remembered, so that polling does not re-run it at once (s)."""


def _json(raw: bytes | str | None) -> Any:
    return json.loads(raw) if raw else None


def get_checkpoint(redis: Redis, calibration_id: str, chain: int) -> dict[str, Any] | None:
    """A chain's last checkpoint (a dict), or None."""
    return _json(redis.get(keys.chain_checkpoint(calibration_id, chain)))


def save_checkpoint(redis: Redis, calibration_id: str, chain: int, state: dict[str, Any]) -> None:
    """Store a chain's annealing state so that a retried chain resumes from it."""
    redis.set(keys.chain_checkpoint(calibration_id, chain), json.dumps(state), ex=SCRATCH_TTL)


def drop_checkpoint(redis: Redis, calibration_id: str, chain: int) -> None:
    """Forget a chain's checkpoint (the chain failed for good)."""
    redis.delete(keys.chain_checkpoint(calibration_id, chain))


def has_chain_result(redis: Redis, calibration_id: str, chain: int) -> bool:
    return bool(redis.exists(keys.chain_result(calibration_id, chain)))


def has_reduced_basis(redis: Redis, calibration_id: str) -> bool:
    return bool(redis.hexists(keys.reduced_basis(calibration_id), "arrays"))


def save_reduced_basis(
    redis: Redis, calibration_id: str, layout: dict[str, Any], arrays: bytes
) -> None:
    """Store the calibration's first reduced basis (its ``layout`` as JSON and its raw
    ``arrays``) in one MULTI/EXEC."""
    key = keys.reduced_basis(calibration_id)
    pipe = redis.pipeline()
    pipe.hset(key, mapping={"layout": json.dumps(layout), "arrays": arrays})
    pipe.expire(key, SCRATCH_TTL)
    pipe.execute()


def get_reduced_basis(redis: Redis, calibration_id: str) -> tuple[dict[str, Any], bytes] | None:
    """(layout, raw arrays) of the calibration's first reduced basis, or None (not built)."""
    layout, arrays = redis.hmget(keys.reduced_basis(calibration_id), ["layout", "arrays"])
    if layout is None or arrays is None:
        return None
    return _json(layout), arrays.encode() if isinstance(arrays, str) else bytes(arrays)


def save_damping_targets(redis: Redis, calibration_id: str, shape: list[int], raw: bytes) -> None:
    """Store the static equilibria (``shape`` (L, N, 3), ``raw`` float64, m) that the damping
    stage's runs settle towards (the target criterion of fpm.dynamics.settle), for its tasks on
    other workers."""
    key = keys.damping_targets(calibration_id)
    pipe = redis.pipeline()
    pipe.hset(key, mapping={"shape": json.dumps(shape), "arrays": raw})
    pipe.expire(key, SCRATCH_TTL)
    pipe.execute()


def get_damping_targets(redis: Redis, calibration_id: str) -> tuple[list[int], bytes] | None:
    """(shape, raw float64) of :func:`save_damping_targets`, or None (not stored)."""
    shape, raw = redis.hmget(keys.damping_targets(calibration_id), ["shape", "arrays"])
    if shape is None or raw is None:
        return None
    return _json(shape), raw.encode() if isinstance(raw, str) else bytes(raw)


def save_chain_result(
    redis: Redis, calibration_id: str, chain: int, result: dict[str, Any], evaluations: int
) -> None:
    """Store a finished chain's result, drop its checkpoint and count its cost evaluations (the
    metrics' counter), in one MULTI/EXEC."""
    pipe = redis.pipeline()
    pipe.set(keys.chain_result(calibration_id, chain), json.dumps(result), ex=SCRATCH_TTL)
    pipe.delete(keys.chain_checkpoint(calibration_id, chain))
    pipe.incrby(keys.evaluations_total(), evaluations)
    pipe.execute()


def save_fitted_chain(
    redis: Redis, stiffness_hash: str, chain: int, result: dict[str, Any]
) -> None:
    """Keep a finished chain's result by the identity of its fit
    (:func:`store.hashing.stiffness_hash`) for :data:`SCRATCH_TTL` s, for later calibrations
    of the same fit."""
    redis.set(keys.fitted_chain(stiffness_hash, chain), json.dumps(result), ex=SCRATCH_TTL)


def get_fitted_chain(redis: Redis, stiffness_hash: str, chain: int) -> dict[str, Any] | None:
    """A chain's result as an earlier calibration of the same fit kept it, or None."""
    return _json(redis.get(keys.fitted_chain(stiffness_hash, chain)))


def get_chain_results(redis: Redis, calibration_id: str, chains: int) -> list[Any]:
    """Each chain's result dict, None for a chain that has not finished: list of ``chains``."""
    raws = redis.mget([keys.chain_result(calibration_id, c) for c in range(chains)])
    return [_json(raw) for raw in raws]


def has_damping_result(redis: Redis, calibration_id: str) -> bool:
    return bool(redis.exists(keys.damping_result(calibration_id)))


def save_damping_result(redis: Redis, calibration_id: str, stage: dict[str, Any]) -> None:
    redis.set(keys.damping_result(calibration_id), json.dumps(stage), ex=SCRATCH_TTL)


def get_damping_result(redis: Redis, calibration_id: str) -> dict[str, Any] | None:
    return _json(redis.get(keys.damping_result(calibration_id)))


def delete_stage_data(
    pipe: Any, calibration_id: str, chains: int, tasks: list[str] | None = None
) -> None:
    """Queue dropping the checkpoints, the reduced basis, the damping result and the load-case
    ``tasks`` (:func:`case_tasks`) once the calibration is done (``pipe``: a pipeline, so that
    it happens with the write of the parameter set)."""
    pipe.delete(*[keys.chain_checkpoint(calibration_id, c) for c in range(chains)])
    pipe.delete(keys.reduced_basis(calibration_id))
    pipe.delete(keys.damping_targets(calibration_id))
    pipe.delete(keys.damping_result(calibration_id))
    for task in tasks or []:
        pipe.delete(keys.case_run(calibration_id, task))
    pipe.delete(keys.case_runs(calibration_id))


CLAIM_TTL = 10
"""Seconds a load-case task's claim lasts unless its holder renews it (:func:`claim_case`); a
holder that died leaves the task to another after at most this long."""


def add_case_task(redis: Redis, calibration_id: str, task: str, spec: dict[str, Any]) -> None:
    """Store what load-case task ``task`` (its digest) runs, unless stored already."""
    pipe = redis.pipeline()
    pipe.hsetnx(keys.case_run(calibration_id, task), "task", json.dumps(spec))
    pipe.expire(keys.case_run(calibration_id, task), SCRATCH_TTL)
    pipe.sadd(keys.case_runs(calibration_id), task)
    pipe.expire(keys.case_runs(calibration_id), SCRATCH_TTL)
    pipe.execute()


def get_case_task(redis: Redis, calibration_id: str, task: str) -> dict[str, Any] | None:
    """What load-case task ``task`` runs, or None (unknown or dropped)."""
    return _json(redis.hget(keys.case_run(calibration_id, task), "task"))


def case_tasks(redis: Redis, calibration_id: str) -> list[str]:
    """The digests of a calibration's load-case tasks."""
    members = redis.smembers(keys.case_runs(calibration_id))
    return sorted(t.decode() if isinstance(t, bytes) else str(t) for t in members)


def has_case_run(redis: Redis, calibration_id: str, task: str) -> bool:
    return bool(redis.hexists(keys.case_run(calibration_id, task), "run"))


def claim_case(redis: Redis, calibration_id: str, task: str, holder: str) -> bool:
    """True for the one caller that runs the task now (SET NX for CLAIM_TTL seconds); False if
    another holds it or it has run."""
    if has_case_run(redis, calibration_id, task):
        return False
    claim = keys.case_claim(calibration_id, task)
    return bool(redis.set(claim, holder, nx=True, ex=CLAIM_TTL))


def is_claimed(redis: Redis, calibration_id: str, task: str) -> bool:
    """Someone holds the task now (:func:`claim_case`)."""
    return bool(redis.exists(keys.case_claim(calibration_id, task)))


def renew_claim(redis: Redis, calibration_id: str, task: str, holder: str) -> bool:
    """Extend ``holder``'s claim by CLAIM_TTL seconds; False if it no longer holds it."""
    claim = keys.case_claim(calibration_id, task)
    pipe = redis.pipeline()
    pipe.get(claim)
    pipe.expire(claim, CLAIM_TTL)
    held = pipe.execute()[0]
    return held is not None and (held.decode() if isinstance(held, bytes) else held) == holder


def release_claim(redis: Redis, calibration_id: str, task: str) -> None:
    """Give the task up (its holder failed before storing a run): another may claim it."""
    redis.delete(keys.case_claim(calibration_id, task))


def name_later(redis: Redis, calibration_id: str, task: str, named: dict[str, Any]) -> None:
    """Name, once, what request task ``task`` learns once its runs have started
    (:func:`fpm.fitting.damping.lockstep.named_later`: its caps)."""
    redis.hsetnx(keys.case_run(calibration_id, task), "named", json.dumps(named))


def named_later(redis: Redis, calibration_id: str, task: str) -> dict[str, Any] | None:
    """What :func:`name_later` named for request task ``task``, or None (not yet)."""
    return _json(redis.hget(keys.case_run(calibration_id, task), "named"))


def save_case_run(
    redis: Redis, calibration_id: str, task: str, run: dict[str, Any], displacements: bytes
) -> None:
    """Store a load-case task's run once (a second writer of the same deterministic run
    changes nothing) and release its claim, in one MULTI/EXEC."""
    key = keys.case_run(calibration_id, task)
    pipe = redis.pipeline()
    pipe.hsetnx(key, "displacements", displacements)
    pipe.hsetnx(key, "run", json.dumps(run))
    pipe.expire(key, SCRATCH_TTL)
    pipe.delete(keys.case_claim(calibration_id, task))
    pipe.execute()


def get_case_run(
    redis: Redis, calibration_id: str, task: str
) -> tuple[dict[str, Any], bytes] | None:
    """A load-case task's run (JSON dict, raw displacements), or None (not run yet)."""
    run, displacements = redis.hmget(keys.case_run(calibration_id, task), ["run", "displacements"])
    if run is None:
        return None
    raw = displacements or b""
    return _json(run), raw.encode() if isinstance(raw, str) else bytes(raw)


def add_span(redis: Redis, calibration_id: str, span: dict[str, Any]) -> None:
    """Append one job's span (:class:`store.timeline.Span` as a dict) to the calibration's."""
    key = keys.calibration_jobs(calibration_id)
    pipe = redis.pipeline()
    pipe.rpush(key, json.dumps(span))
    pipe.expire(key, SCRATCH_TTL)
    pipe.execute()


def get_spans(redis: Redis, calibration_id: str) -> list[dict[str, Any]]:
    """The spans of the calibration's jobs so far, in the order they were added."""
    return [json.loads(raw) for raw in redis.lrange(keys.calibration_jobs(calibration_id), 0, -1)]


def report_progress(redis: Redis, calibration_id: str, field: str, info: dict[str, Any]) -> bool:
    """Write one progress report (``field``: a chain index or ``keys.DAMPING_PROGRESS``) and
    say whether the calibration goes on: False once it is finished (canceled, failed) or gone."""
    key = keys.calibration_progress(calibration_id)
    pipe = redis.pipeline()
    pipe.hset(key, field, json.dumps(info))
    pipe.expire(key, SCRATCH_TTL)
    pipe.hget(keys.calibration(calibration_id), "status")
    status = pipe.execute()[-1]
    return status is not None and not CalibrationStatus(status.decode()).terminal


def profile_key(calibration_id: str) -> str:
    """String: JSON profile data of a succeeded calibration."""
    return f"{keys.calibration(calibration_id)}:profile"


def has_profile(redis: Redis, calibration_id: str) -> bool:
    return bool(redis.exists(profile_key(calibration_id)))


def get_profile(redis: Redis, calibration_id: str) -> dict[str, Any] | None:
    """``{"status": "ready", "h", "load_cases"}`` or ``{"status": "failed", "error"}``, or None
    (not computed, or expired)."""
    return _json(redis.get(profile_key(calibration_id)))


def save_profile(redis: Redis, calibration_id: str, data: dict[str, Any]) -> None:
    """Store profile data; a failed one (``data["status"] == "failed"``) only for
    :data:`PROFILE_FAILED_TTL` seconds."""
    ttl = PROFILE_FAILED_TTL if data.get("status") == "failed" else SCRATCH_TTL
    redis.set(profile_key(calibration_id), json.dumps(data), ex=ttl)


def get_export(redis: Redis, export_hash: str) -> bytes | None:
    """The cached export, gzip-compressed (:func:`save_export`), or None (not made yet, or
    expired)."""
    raw = redis.get(keys.export(export_hash))
    if raw is None:
        return None
    return raw.encode() if isinstance(raw, str) else bytes(raw)


def has_export(redis: Redis, export_hash: str) -> bool:
    return bool(redis.exists(keys.export(export_hash)))


def save_export(redis: Redis, export_hash: str, body: bytes) -> None:
    """Cache an export for :data:`EXPORT_TTL` seconds, gzip-compressed here, in the worker (the
    formats are text: a 97,336-node json export shrinks from 86 MB to about a sixth, so the
    API reads and sends a sixth of the bytes and Redis keeps a sixth); forget an earlier
    failure of it and release the claim of its job (:func:`claim_export`)."""
    pipe = redis.pipeline()
    pipe.set(keys.export(export_hash), gzip.compress(body, EXPORT_GZIP_LEVEL), ex=EXPORT_TTL)
    pipe.delete(keys.export_failure(export_hash), keys.export_claim(export_hash))
    pipe.execute()


def save_export_failure(redis: Redis, export_hash: str, error: str, invalid: bool) -> None:
    """Remember for :data:`EXPORT_FAILED_TTL` seconds that an export failed: ``invalid`` when
    the parameters do not fit the spec's lattice (the same input fails again), else any other
    error (a retry after the cool-down may succeed). Releases the claim of its job."""
    data = json.dumps({"error": error, "invalid": invalid})
    pipe = redis.pipeline()
    pipe.set(keys.export_failure(export_hash), data, ex=EXPORT_FAILED_TTL)
    pipe.delete(keys.export_claim(export_hash))
    pipe.execute()


def get_export_failure(redis: Redis, export_hash: str) -> tuple[dict[str, Any], int] | None:
    """``({"error", "invalid"}, seconds left of the cool-down)`` of a failed export, or None."""
    pipe = redis.pipeline()
    pipe.get(keys.export_failure(export_hash))
    pipe.ttl(keys.export_failure(export_hash))
    raw, ttl = pipe.execute()
    if raw is None:
        return None
    return _json(raw), max(int(ttl), 1)


def claim_export(redis: Redis, export_hash: str, seconds: int = 10) -> bool:
    """True for the one caller that may enqueue the export job now: SET NX for ``seconds``
    (which covers the moment between a request's finding no job and its enqueueing one; later
    requests find the job), released when the job stores its export or its failure."""
    return bool(redis.set(keys.export_claim(export_hash), b"1", nx=True, ex=seconds))
