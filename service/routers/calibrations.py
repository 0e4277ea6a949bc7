"""/v1/calibrations: submit, read, list, cancel."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Response, status
from pydantic import TypeAdapter

from fpm import ProblemSpec
from fpm.model.problem import case_name
from fpm.model.spec import AnnealingSettings
from store import graph, quotas, records
from store.status import CalibrationStatus, FemStatus, Phase, calibration_stages

from ..deps import CalibrationId, OwnerDep, RedisDep, SettingsDep
from ..errors import ProblemError, problem_responses
from ..examples import openapi_examples
from ..finished import FinishedAnswers
from ..limits import (
    check_calibration_spec,
    check_reference_mesh,
    dump_spec,
    supplied_reference,
)
from ..schemas import (
    Calibration,
    CalibrationPage,
    CalibrationResult,
    CalibrationSummary,
    ChainProgress,
    DampingProgress,
    FemProgress,
    Progress,
    Timings,
)

router = APIRouter(prefix="/v1/calibrations", tags=["calibrations"])

MAX_OFFSET = 10**9
"""Largest listing offset (Redis range indexes are 64-bit: 2**63 answered 500)."""

DAMPING_STEPS = {
    "polish": "polishing the stiffness",
    "depth": "choosing the depth",
    "field": "fitting the stiffness field",
    "damping": "finding the fastest-settling d",
}
LEGACY_RESULT = (
    "this result was stored by an older version of the service (no relative discrepancy): "
    "resubmit the spec to calibrate it again"
)

SpecBody = Annotated[ProblemSpec, Body(openapi_examples=openapi_examples())]
ANSWER = TypeAdapter(Calibration)
"""Serialises an answer as FastAPI serialises a route's response model."""
FINISHED = FinishedAnswers()
"""The answers of succeeded calibrations polled lately (:mod:`service.finished`)."""


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    operation_id="submit_calibration",
    responses={
        200: {"model": Calibration, "description": "the identical spec's calibration"},
        **problem_responses(400, 413, 422, 429),
    },
)
def submit(
    spec: SpecBody, redis: RedisDep, settings: SettingsDep, owner: OwnerDep, response: Response
) -> Calibration:
    """Start a calibration (202 + Location).

    An identical spec (after defaults) already queued, running or succeeded returns that
    calibration with 200 instead; a failed or canceled one is started afresh. A new calibration
    that would take the API key over its quota (calibrations queued or running, their lattice
    nodes) is refused with 429 and Retry-After; other keys are not affected.
    """
    mesh = check_reference_mesh(spec, redis)  # the upload reference.mesh_id names
    problem = check_calibration_spec(spec, settings, mesh)
    dumped = dump_spec(spec)
    if graph.answered_by(redis, dumped) is None:
        _check_quota(redis, settings, owner, problem.n_nodes)
    record, created = graph.submit_calibration(
        redis, dumped, settings.job_options, supplied_reference(problem)
    )
    if created:
        quotas.add(redis, owner, record.id, problem.n_nodes)
    response.headers["Location"] = f"{router.prefix}/{record.id}"
    if not created:
        response.status_code = status.HTTP_200_OK
    return read(record.id, redis)


def _check_quota(redis: Any, settings: Any, owner: str, nodes: int) -> None:
    """429 when a new calibration of ``nodes`` nodes takes ``owner`` over a quota."""
    used = quotas.usage(redis, owner)
    over = []
    if settings.max_active_per_key and used.active + 1 > settings.max_active_per_key:
        over.append(
            f"this API key has {used.active} calibrations queued or running (limit "
            f"{settings.max_active_per_key})"
        )
    if settings.max_nodes_per_key and used.nodes + nodes > settings.max_nodes_per_key:
        over.append(
            f"its calibrations in flight hold {used.nodes:,} lattice nodes and this one "
            f"{nodes:,} (limit {settings.max_nodes_per_key:,})"
        )
    if over:
        raise ProblemError(
            429,
            "Too many requests",
            "; ".join(over) + ": wait for one to finish (or cancel one), then submit again",
            headers={"Retry-After": str(settings.quota_retry_after)},
            active=used.active,
            nodes_in_flight=used.nodes,
        )


@router.get("", operation_id="list_calibrations", responses=problem_responses(422))
def listing(
    redis: RedisDep,
    settings: SettingsDep,
    status_filter: Annotated[CalibrationStatus | None, Query(alias="status")] = None,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
) -> CalibrationPage:
    """Calibrations, newest first; ``status`` filters."""
    limit = min(limit, settings.page_size_limit)
    total, page = records.calibration_page(redis, offset, limit, status_filter)
    items = [
        CalibrationSummary(
            id=r.id,
            name=r.name,
            status=CalibrationStatus.RUNNING if _fem_running(redis, r) else r.status,
            created=r.created,
            parameter_set_id=r.parameter_set_id or None,
        )
        for r in page
    ]
    return CalibrationPage(items=items, total=total, offset=offset, limit=limit)


@router.get(
    "/{calibration_id}",
    operation_id="get_calibration",
    response_model=Calibration,
    responses=problem_responses(404),
)
def poll(calibration_id: CalibrationId, redis: RedisDep) -> Response:
    """Status, progress, and when done the result."""
    body = FINISHED.get(redis, calibration_id)
    if body is None:
        calibration, stamp = read_view(calibration_id, redis)
        body = ANSWER.dump_json(calibration, by_alias=True)
        if calibration.status == CalibrationStatus.SUCCEEDED:
            FINISHED.put(calibration_id, stamp, body)
    return Response(body, media_type="application/json")


def read(calibration_id: str, redis: Any) -> Calibration:
    """The calibration's API view (404 if there is none)."""
    return read_view(calibration_id, redis)[0]


def read_view(calibration_id: str, redis: Any) -> tuple[Calibration, tuple[str, ...]]:
    """The API view and the record's stamp (:func:`store.records.calibration_stamp`), read in
    one round trip (404 if there is none)."""
    view = records.get_calibration_view(redis, calibration_id)
    if view is None:
        raise ProblemError(404, "Not found", f"no calibration {calibration_id!r}")
    record, chains, damping, stamp = view
    meta = _fem_running(redis, record)
    fem = None if meta is None else _fem_progress(meta)
    return _view(record, (chains, damping), fem), stamp


def _fem_running(redis: Any, record: records.CalibrationRecord) -> dict[str, str] | None:
    """The meta of the FEM reference a queued calibration waits on while it runs (the
    calibration is then shown running, in its stage 1: the record stays queued until its
    chains start), else None."""
    if record.status != CalibrationStatus.QUEUED or record.fem_cached:
        return None
    meta = records.get_fem_meta(redis, record.fem_hash)
    return meta if meta.get("status") == FemStatus.RUNNING.value else None


def _fem_progress(meta: dict[str, str]) -> FemProgress:
    """The running FEM reference's level, from its meta hash (the worker writes it as each
    level starts: :func:`worker.jobs.fem_reference`); empty before the first."""
    if "level" not in meta:
        return FemProgress()
    change = json.loads(meta.get("last_change") or "null")
    return FemProgress(
        level=int(meta["level"]), fem_nodes=int(meta["fem_nodes"]), last_change=change
    )


@router.delete(
    "/{calibration_id}", operation_id="cancel_calibration", responses=problem_responses(404, 409)
)
def cancel(calibration_id: CalibrationId, redis: RedisDep) -> Calibration:
    """Cancel: running chains are stopped, queued jobs dropped, the status becomes canceled.

    Canceling a canceled calibration is a no-op; a succeeded or failed one answers 409.
    """
    record = records.get_calibration(redis, calibration_id)
    if record is None:
        raise ProblemError(404, "Not found", f"no calibration {calibration_id!r}")
    if not graph.cancel_calibration(redis, calibration_id) and record.status in (
        CalibrationStatus.SUCCEEDED,
        CalibrationStatus.FAILED,
    ):
        raise ProblemError(
            409, "Conflict", f"calibration {calibration_id} already {record.status.value}"
        )
    return read(calibration_id, redis)


def _stage(
    method: str,
    phase: Phase,
    damping: DampingProgress | None,
    fem: FemProgress | None = None,
    reused: bool = False,
) -> str:
    """What runs in ``phase``, in words, after its number among the stages ("stage 2 of 4: ...",
    :func:`store.status.calibration_stages`; ``reused``: the FEM reference was stored)."""
    stages = calibration_stages(method)
    words = _stage_words(method, phase, damping, fem)
    if phase not in stages:
        return words + (" (FEM reference reused)" if reused and phase == Phase.QUEUED else "")
    return f"stage {stages.index(phase) + 1} of {len(stages)}: {words}"


def _stage_words(
    method: str, phase: Phase, damping: DampingProgress | None, fem: FemProgress | None
) -> str:
    if phase == Phase.FEM and fem is not None and fem.level is not None:
        return f"FEM reference (refinement level {fem.level}: {fem.fem_nodes:,} FEM nodes)"
    if phase == Phase.ANNEALING:
        if method == "two-stage":
            return "stiffness search (annealing on static equilibria)"
        return "annealing (k, d) on dynamic runs"
    if phase == Phase.DAMPING:
        step = DAMPING_STEPS.get(damping.step or "", "starting") if damping else "starting"
        return f"damping ({step})"
    return {
        Phase.QUEUED: "queued",
        Phase.FEM: "FEM reference",
        Phase.FINALIZE: "final dynamic run and figures",
        Phase.DONE: "done",
    }[phase]


def _view(
    record: records.CalibrationRecord,
    progress: tuple[dict[int, dict[str, Any]], dict[str, Any] | None],
    fem: FemProgress | None,
) -> Calibration:
    """The API view of a record and its jobs' progress (``fem``: the FEM reference's, while
    it runs for this calibration)."""
    chain_reports, damping_report = progress
    chains = [ChainProgress(chain=c, **p) for c, p in sorted(chain_reports.items())]
    damping = DampingProgress(**damping_report) if damping_report else None
    annealing = record.spec["annealing"]
    method = annealing.get("method", "paper")  # records of older versions ran the paper's
    phase = record.phase
    status_ = record.status
    if fem is not None:
        phase, status_ = Phase.FEM, CalibrationStatus.RUNNING
    stages = calibration_stages(method)
    temperatures = [c.temperature for c in chains if c.temperature is not None]
    costs = [c.best_cost for c in chains if c.best_cost is not None]
    per_chain = max([c.moves for c in chains] or [0]) or AnnealingSettings(**annealing).moves
    result, error = record.result, record.error or None
    if result is not None and "relative_discrepancy" not in result:
        result, error = None, LEGACY_RESULT
    t = Timings(
        created=record.created,
        started=record.started or None,
        finished=record.finished or None,
        queued_seconds=(record.started - record.created) if record.started else None,
        running_seconds=(record.finished - record.started)
        if record.started and record.finished
        else None,
    )
    return Calibration(
        id=record.id,
        name=record.name,
        status=status_,
        progress=Progress(
            phase=phase,
            method=method,
            stage=_stage(method, phase, damping, fem, record.fem_cached),
            stages=stages,
            stage_number=stages.index(phase) + 1 if phase in stages else None,
            iterations=sum(c.move for c in chains),
            total_iterations=per_chain * record.chains,
            temperature=max(temperatures) if temperatures else None,
            best_cost=min(costs) if costs else None,
            chains=chains,
            damping=damping,
            fem=fem,
        ),
        timings=t,
        fem_reference_id=record.fem_hash,
        fem_cached=record.fem_cached,
        load_cases=[
            case_name(case.get("name"), i)
            for i, case in enumerate(record.spec.get("load_cases") or [])
        ],
        result=CalibrationResult(**result) if result else None,
        parameter_set_id=record.parameter_set_id or None,
        error=error,
        spec_hash=record.spec_hash,
    )
