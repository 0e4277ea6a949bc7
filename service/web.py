"""The web view: one HTML page at ``/`` with its script and style sheet (``/web/...``), and the
JSON of the FPM-vs-FEM profile plot (``GET /v1/calibrations/{id}/profile``).

No CDN and no JavaScript library: ``service/static/web`` holds the page, a small vanilla script
that polls the /v1 endpoints (sending ``X-API-Key`` once the user has given one, which it asks
for when the service answers 401) and draws its charts as inline SVG, and the CSS. The page and
its assets carry no data, so they need no key; every figure comes from /v1.

The profile needs an FPM run at the fitted parameters, which only a worker may make (the service
never loads the kernels): the first request enqueues the profile job
(:func:`store.graph.request_profile`) and answers 202 ``pending``, later ones the stored data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Response, status
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from store import graph, records, scratch
from store.status import CalibrationStatus

from . import errors
from .deps import CalibrationId, RedisDep, SettingsDep, require_api_key

STATIC = Path(__file__).resolve().parent / "static" / "web"
"""The page, script and style sheet."""

CONTENT_SECURITY_POLICY = "; ".join(
    [
        "default-src 'none'",
        "script-src 'self'",  # app.js, and the 3D view's modules (view3d.js, vendor/three)
        "worker-src 'self'",
        "style-src 'self'",
        "img-src 'self'",
        "connect-src 'self'",
        "base-uri 'none'",
        "form-action 'self'",
        "frame-ancestors 'none'",
    ]
)
"""The page's Content-Security-Policy: everything from this origin only (scripts, modules and
workers; no inline script or style, no eval), so the page can load nothing from another host."""

PROFILE_FAILED_HINT = "the profile job failed; it is tried again in a few minutes"

page = APIRouter(include_in_schema=False)
api = APIRouter(prefix="/v1/calibrations", tags=["calibrations"])


@page.get("/")
def index() -> FileResponse:
    """The web view (a single page; its routes live in the URL's fragment)."""
    headers = {"Content-Security-Policy": CONTENT_SECURITY_POLICY}
    return FileResponse(STATIC / "index.html", media_type="text/html", headers=headers)


class ProfileCase(BaseModel):
    """One load case's profile: FEM and FPM displacement magnitudes along one line of nodes."""

    name: str
    axis: Literal["x", "y", "z"] = Field(description="the axis the profile line runs along")
    force_axis: Literal["x", "y", "z"] = Field(description="the load case's main force axis")
    nodes: list[int] = Field(description="node indices along the line, in order")
    position: list[float] = Field(description="the nodes' coordinate along the axis, m")
    fem: list[float] = Field(description="FEM displacement magnitude at each node, m")
    fpm: list[float] = Field(
        description="FPM displacement magnitude at each node, m (a run at the fitted stiffness, "
        "d and depth)"
    )
    relative_discrepancy: float = Field(description="the result's, over all nodes, %")
    loaded_discrepancy: float = Field(description="the result's, loaded nodes only, %")
    discrepancy_h: float = Field(description="the result's, % of h (read beside the relative)")
    steps: int = Field(description="time steps of the FPM run")
    settled: bool


class CalibrationProfile(BaseModel):
    """The profile plot's data: ``pending`` while a worker computes it, then ``ready``."""

    calibration_id: str
    status: Literal["pending", "ready", "failed"]
    error: str | None = None
    h: float | None = Field(None, description="shortest spring rest length, m")
    load_cases: list[ProfileCase] = []


@api.get(
    "/{calibration_id}/profile",
    operation_id="get_calibration_profile",
    responses={
        202: {"model": CalibrationProfile, "description": "being computed: ask again"},
        **errors.problem_responses(404),
        409: {
            **errors.problem_responses(409)[409],
            "description": "the calibration has no result (not succeeded)",
        },
    },
)
def calibration_profile(
    calibration_id: CalibrationId, redis: RedisDep, settings: SettingsDep, response: Response
) -> CalibrationProfile:
    """FPM and FEM displacement profiles of a succeeded calibration, per load case.

    The data of ``fpmcal calibrate --plot``'s left panel: along the axis-parallel line through
    the load case's first loaded node that holds the most nodes, the FEM's and the fitted FPM's
    displacement magnitudes, with the result's relative discrepancy (the headline) and % of h.
    The first request starts a worker job and answers 202 (``pending``); ask again.
    """
    stored = scratch.get_profile(redis, calibration_id)
    if stored is not None:
        return CalibrationProfile(calibration_id=calibration_id, **stored)
    record = records.get_calibration(redis, calibration_id)
    if record is None:
        raise errors.ProblemError(404, "Not found", f"no calibration {calibration_id!r}")
    if (
        record.status != CalibrationStatus.SUCCEEDED
        or not record.result
        or "relative_discrepancy" not in record.result
    ):
        raise errors.ProblemError(
            409,
            "Conflict",
            f"calibration {calibration_id} is {record.status.value} with no current result: "
            "profiles are drawn from a succeeded calibration's result",
        )
    if not graph.request_profile(redis, calibration_id, settings.finalize_timeout):
        return CalibrationProfile(
            calibration_id=calibration_id, status="failed", error=PROFILE_FAILED_HINT
        )
    response.status_code = status.HTTP_202_ACCEPTED
    return CalibrationProfile(calibration_id=calibration_id, status="pending")


def install(app: FastAPI, responses: dict[int | str, dict[str, Any]]) -> None:
    """Serve the web view at ``/`` and ``/web/``, and the profile endpoint under /v1 (with the
    API key, like every /v1 route, and the error ``responses`` every /v1 route documents)."""
    app.include_router(page)
    app.mount("/web", StaticFiles(directory=STATIC), name="web")
    app.include_router(api, dependencies=[Depends(require_api_key)], responses=responses)
