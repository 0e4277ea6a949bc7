"""What every job starts from: the RQ job it runs in and the calibration it works for."""

from __future__ import annotations

from redis import Redis
from rq import get_current_job
from rq.job import Job

from store import records


class Canceled(Exception):
    """The calibration was canceled (or failed elsewhere) while this job was running."""


def _job() -> Job:
    job = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    return job


def _calibration_job(calibration_id: str) -> tuple[Job, Redis, records.CalibrationRecord] | None:
    """This job, its connection and calibration ``calibration_id``'s record; None when the
    calibration is gone or has ended (the job has nothing to do)."""
    job = _job()
    redis = job.connection
    record = records.get_calibration(redis, calibration_id)
    if record is None or record.status.terminal:
        return None
    return job, redis, record
