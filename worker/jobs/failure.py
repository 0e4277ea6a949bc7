"""A failed job's record: its calibration failed, or its FEM reference."""

from __future__ import annotations

import time
from typing import Any

from redis import Redis
from rq.job import Job

from store import keys, records
from store.status import CalibrationStatus, FemStatus


def _fail(redis: Redis, calibration_id: str, error: str) -> None:
    records.update_calibration(
        redis,
        calibration_id,
        {"status": CalibrationStatus.FAILED, "error": error, "finished": time.time()},
    )


def on_failure(job: Job, connection: Redis, exc_type: type, value: BaseException, tb: Any) -> None:
    """RQ failure callback of every job: record the failure once no retry is left.

    A calibration job (chain, damping, finalize) fails its calibration, which stops the
    others;
    the FEM job marks its reference failed, and the chains waiting on it then fail their
    calibrations (they run anyway: their dependency allows failure).
    """
    if job.retries_left:
        return
    error = f"{exc_type.__name__}: {value}" if str(value) else exc_type.__name__
    if job.func_name == keys.FEM_JOB:
        failed = {"status": FemStatus.FAILED, "error": error, "finished": time.time()}
        records.update_fem_meta(connection, job.args[0], failed)
    else:
        _fail(connection, job.args[0], f"{job.description}: {error}")
