"""Bytes a worker makes for a stored parameter set (its exports, its 3D view): the steps the
routes share.

Such bytes need the numerical kernels, so this process never makes them: the first request
enqueues the job (:mod:`store.graph`) and answers 202 ``pending`` with ``Retry-After``; once
the job has cached the bytes, the answer is 200 with them. The set's spec comes from its
calibration record (410 when that is gone); a job that failed on the input answers 422, one
that failed otherwise 503 with ``Retry-After`` (its cool-down).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from redis import Redis

from store import records
from store.graph import ExportState
from store.text import escape

from .errors import ProblemError, problem_responses

RETRY_HEADERS = {
    "Retry-After": {
        "description": "seconds to wait before asking again",
        "schema": {"type": "integer"},
    }
}


class ExportPending(BaseModel):
    """A worker is making the bytes (an export, a 3D view): ask again after ``retry_after``
    seconds. (Named for the export, its first use, in the OpenAPI document.)"""

    status: Literal["pending"] = "pending"
    retry_after: int = Field(description="seconds to wait before asking again (as Retry-After)")


def responses(kind: str, ok: dict[str, Any]) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI responses of a route whose bytes a ``kind`` job makes (``export``), 200 being
    ``ok``."""
    return {
        200: ok,
        202: {
            "model": ExportPending,
            "description": f"a worker is making the {kind}: ask again after Retry-After seconds "
            "(Location: this URL)",
            "headers": {
                **RETRY_HEADERS,
                "Location": {"description": "where to ask", "schema": {"type": "string"}},
            },
        },
        **problem_responses(404, 410, 422),
        503: {
            **problem_responses(503)[503],
            "description": f"Redis unreachable, or the {kind} job failed: it is tried again after "
            "Retry-After seconds",
            "headers": RETRY_HEADERS,
        },
    }


def requested(
    redis: Redis,
    parameter_set_id: str,
    ps: dict[str, Any],
    request: Callable[[dict[str, Any]], ExportState],
    what: str,
    location: str,
) -> bytes | JSONResponse:
    """The cached bytes of stored parameter set ``ps``, or the 202 answer while its job runs.

    Args:
        request: asks :mod:`store.graph` for the bytes given the set's spec (enqueues the job
            unless it is queued or cached).
        what: the job's name in messages (``the export ... as vtu``, ``the 3D view job``).
        location: the URL to ask again (the 202's ``Location``).

    Raises:
        ProblemError: 410 (the calibration holding the spec is gone), 422 (the parameters do not
            fit the spec's lattice), 503 (the job failed; tried again after ``Retry-After``).
    """
    provenance = ps.get("provenance") or {}
    record = records.get_calibration(redis, str(provenance.get("calibration_id", "")))
    if record is None or record.spec_hash != provenance.get("spec_hash"):
        raise ProblemError(
            410,
            "Gone",
            f"the calibration that holds the spec of parameter set {parameter_set_id} is "
            "gone: calibrate its spec again",
        )
    state = request(record.spec)
    if state.invalid:
        error = escape(state.error or "")
        raise ProblemError(
            422,
            "Invalid input",
            f"parameter set {parameter_set_id} does not fit its spec's lattice: {error}",
            errors=[{"field": "parameter_set_id", "message": error}],
        )
    if state.error is not None:
        raise ProblemError(
            503,
            "Service unavailable",
            f"{what} failed ({escape(state.error)}); it is tried again in {state.retry_after} s",
            headers={"Retry-After": str(state.retry_after)},
        )
    if state.body is None:
        return JSONResponse(
            ExportPending(retry_after=state.retry_after).model_dump(),
            status_code=202,
            headers={"Retry-After": str(state.retry_after), "Location": location},
        )
    return state.body
