"""RQ job functions: FEM reference, one annealing chain, finalize (enqueued by dotted path).

Every job takes ids only and reads what it needs from our keys; every job may run twice
(a retry after its worker died) and writes its results once, under deterministic keys:
a finished chain is not re-run, a stopped chain resumes from its checkpoint, and the
parameter set is written with SET NX.
"""

from __future__ import annotations

import json
import time
from typing import Any

from redis import Redis
from rq import get_current_job
from rq.job import Job

from fpm import load_problem
from fpm.annealing import AnnealingError
from fpm.calibration import ChainResult, finalize, run_chain
from fpm.fem import FemError, FemResult, solve_fem

from . import keys, store
from .status import CalibrationStatus, FemStatus, Phase

PROGRESS_INTERVAL = 0.5
"""Seconds between progress writes of a chain (each also checks for a cancel)."""


class Canceled(Exception):
    """The calibration was canceled (or failed elsewhere) while this chain was running."""


def _job() -> Job:
    job = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    return job


def fem_reference(fem_hash: str) -> dict[str, Any]:
    """Solve and store the FEM reference ``fem_hash`` (no expiry). Returns a summary."""
    redis = _job().connection
    meta_key = keys.fem_meta(fem_hash)
    if redis.exists(keys.fem_reference(fem_hash)):
        return {"id": fem_hash, "cached": True}
    meta = store.get_fem_meta(redis, fem_hash)
    redis.hset(meta_key, mapping={"status": FemStatus.RUNNING.value, "started": time.time()})
    try:
        result = solve_fem(load_problem(json.loads(meta["spec"])))
    except FemError as e:
        # The problem cannot be solved (e.g. the solid is not held): a retry would fail the
        # same way, so the reference fails now and the chains waiting on it say why.
        failed: store.Mapping = {
            "status": FemStatus.FAILED.value,
            "error": str(e),
            "finished": time.time(),
        }
        redis.hset(meta_key, mapping=failed)
        return {"id": fem_hash, "failed": True}
    fields: store.Mapping = {
        "status": FemStatus.SUCCEEDED.value,
        "finished": time.time(),
        "n_nodes": len(result.nodes),
        "load_cases": json.dumps(result.load_cases),
    }
    pipe = redis.pipeline()
    pipe.set(keys.fem_reference(fem_hash), json.dumps(result.to_dict()))
    pipe.hset(meta_key, mapping=fields)
    pipe.execute()
    return {"id": fem_hash, "cached": False, "n_nodes": len(result.nodes)}


def anneal_chain(calibration_id: str, chain: int) -> dict[str, Any]:
    """Run one annealing chain of a calibration and store its ChainResult."""
    job = _job()
    redis = job.connection
    record = store.get_calibration(redis, calibration_id)
    if record is None or record.status.terminal:
        return {"skipped": True}
    result_key = keys.chain_result(calibration_id, chain)
    if redis.exists(result_key):
        return {"skipped": True}
    reference = store.get_fem_reference(redis, record.fem_hash)
    if reference is None:
        error = store.get_fem_meta(redis, record.fem_hash).get("error") or "not computed"
        _fail(redis, calibration_id, f"FEM reference failed: {error}")
        return {"failed": True}
    store.update_calibration(
        redis,
        calibration_id,
        {
            "status": CalibrationStatus.RUNNING,
            "phase": Phase.ANNEALING,
            "started": record.started or time.time(),
        },
    )
    problem = load_problem(record.spec)
    checkpoint_key = keys.chain_checkpoint(calibration_id, chain)
    saved = redis.get(checkpoint_key)
    reporter = _ProgressReporter(job, calibration_id, chain)
    try:
        result = run_chain(
            problem,
            FemResult.from_dict(reference),
            chain,
            progress=reporter,
            checkpoint=lambda state: store.save_checkpoint(redis, checkpoint_key, state),
            resume=json.loads(saved) if saved else None,
        )
    except Canceled:
        return {"canceled": True}
    except AnnealingError as e:
        # The spec cannot be fitted (e.g. every candidate diverges): a retry would fail the
        # same way, so the calibration fails now, with the annealer's reason.
        _fail(redis, calibration_id, f"annealing chain {chain} failed: {e}")
        redis.delete(checkpoint_key)
        return {"failed": True}
    reporter.flush()
    pipe = redis.pipeline()
    pipe.set(result_key, json.dumps(result.to_dict()), ex=store.SCRATCH_TTL)
    pipe.delete(checkpoint_key)
    pipe.execute()
    return {"k": result.k, "d": result.d, "cost": result.cost}


class _ProgressReporter:
    """Writes a chain's progress to the calibration's progress hash and to the job meta.

    At most every PROGRESS_INTERVAL seconds; each write also reads the calibration's status
    and raises :class:`Canceled` once it is terminal, so a canceled chain stops even on a
    worker that cannot kill its work horse (SimpleWorker).
    """

    def __init__(self, job: Job, calibration_id: str, chain: int):
        self.job = job
        self.calibration_id = calibration_id
        self.chain = chain
        self.last = 0.0
        self.info: dict[str, Any] = {}

    def __call__(self, info: dict[str, Any]) -> None:
        self.info = {k: info[k] for k in ("move", "moves", "temperature", "best_cost") if k in info}
        if time.monotonic() - self.last >= PROGRESS_INTERVAL:
            self.flush()

    def flush(self) -> None:
        """Write the latest report now."""
        self.last = time.monotonic()
        redis = self.job.connection
        key = keys.calibration_progress(self.calibration_id)
        pipe = redis.pipeline()
        pipe.hset(key, str(self.chain), json.dumps(self.info))
        pipe.expire(key, store.SCRATCH_TTL)
        pipe.hget(keys.calibration(self.calibration_id), "status")
        status = pipe.execute()[-1]
        self.job.meta["progress"] = self.info
        self.job.save_meta()
        if status is None or CalibrationStatus(status.decode()).terminal:
            raise Canceled(self.calibration_id)


def finalize_calibration(calibration_id: str) -> dict[str, Any]:
    """Pick the best chain, resolve the depth, store the parameter set and the result."""
    redis = _job().connection
    record = store.get_calibration(redis, calibration_id)
    if record is None or record.status.terminal:
        return {"skipped": True}
    store.update_calibration(redis, calibration_id, {"phase": Phase.FINALIZE})
    raws = redis.mget([keys.chain_result(calibration_id, c) for c in range(record.chains)])
    missing = [c for c, raw in enumerate(raws) if raw is None]
    if missing:
        _fail(redis, calibration_id, f"chain(s) {missing} did not finish")
        return {"failed": True}
    reference = store.get_fem_reference(redis, record.fem_hash)
    if reference is None:
        _fail(redis, calibration_id, "the FEM reference is gone")
        return {"failed": True}
    problem = load_problem(record.spec)
    chains = [ChainResult.from_dict(json.loads(raw)) for raw in raws if raw is not None]
    result = finalize(problem, FemResult.from_dict(reference), chains).to_dict()
    parameter_set = _parameter_set(record, result, problem.n_nodes)

    def store_once(pipe: Any) -> None:
        store.write_parameter_set(pipe, parameter_set)
        pipe.delete(*[keys.chain_checkpoint(calibration_id, c) for c in range(record.chains)])

    store.update_calibration(
        redis,
        calibration_id,
        {
            "status": CalibrationStatus.SUCCEEDED,
            "phase": Phase.DONE,
            "finished": time.time(),
            "result": result,
            "parameter_set_id": parameter_set["id"],
        },
        extra=store_once,
    )
    return {"parameter_set_id": parameter_set["id"]}


def _parameter_set(record: store.CalibrationRecord, result: dict[str, Any], n_nodes: int) -> dict:
    """The stored (k, d, depth) with the material, a geometry summary and the provenance.

    Its id comes from the spec hash, so one spec stores at most one parameter set.
    """
    spec = record.spec
    geometry = spec["geometry"]
    return {
        "id": f"ps-{record.spec_hash[:16]}",
        "created": time.time(),
        "name": record.name,
        "k": result["k"],
        "d": result["d"],
        "depth": result["depth"],
        "dt": spec["fpm"]["dt"],
        "stiffness_scale": spec["fpm"]["stiffness_scale"],
        "material": spec["material"],
        "geometry": {
            "type": geometry["type"],
            "connectivity": geometry.get("connectivity"),
            "size": geometry.get("size"),
            "nodes": n_nodes,
            "h": result["h"],
        },
        "discrepancy": result["discrepancy"],
        "cost": result["cost"],
        "provenance": {
            "calibration_id": record.id,
            "spec_hash": record.spec_hash,
            "fem_hash": record.fem_hash,
            "seed": spec["annealing"]["seed"],
            "chains": record.chains,
            "evaluations": result["evaluations"],
        },
    }


def _fail(redis: Redis, calibration_id: str, error: str) -> None:
    store.update_calibration(
        redis,
        calibration_id,
        {"status": CalibrationStatus.FAILED, "error": error, "finished": time.time()},
    )


def on_failure(job: Job, connection: Redis, exc_type: type, value: BaseException, tb: Any) -> None:
    """RQ failure callback of every job: record the failure once no retry is left.

    A calibration job (chain, finalize) fails its calibration, which stops the other chains;
    the FEM job marks its reference failed, and the chains waiting on it then fail their
    calibrations (they run anyway: their dependency allows failure).
    """
    if job.retries_left:
        return
    error = f"{exc_type.__name__}: {value}" if str(value) else exc_type.__name__
    if job.func_name == "worker.jobs.fem_reference":
        fields: store.Mapping = {
            "status": FemStatus.FAILED.value,
            "error": error,
            "finished": time.time(),
        }
        connection.hset(keys.fem_meta(job.args[0]), mapping=fields)
    else:
        _fail(connection, job.args[0], f"{job.description}: {error}")
