"""/v1/fem-references: the FEM reference of a spec on its own."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Body, Query, Response, status

from fpm import ProblemSpec
from store import graph, records
from store.hashing import fem_hash
from store.status import FemStatus

from ..deps import FemId, RedisDep, SettingsDep
from ..errors import ProblemError, problem_responses
from ..examples import openapi_examples
from ..limits import (
    check_calibration_spec,
    check_reference_mesh,
    dump_spec,
    supplied_reference,
)
from ..schemas import FemReference

router = APIRouter(prefix="/v1/fem-references", tags=["fem-references"])


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    operation_id="submit_fem_reference",
    responses={
        200: {"model": FemReference, "description": "already computed or on its way"},
        **problem_responses(400, 413, 422),
    },
)
def submit(
    spec: Annotated[ProblemSpec, Body(openapi_examples=openapi_examples())],
    redis: RedisDep,
    settings: SettingsDep,
    response: Response,
) -> FemReference:
    """Compute the FEM reference of a spec (only geometry, material, fixed and load cases count).

    202 + Location when a job was started; 200 + Location when the same reference is already
    stored or being computed. Its id is the content hash, so it can be shared.
    """
    mesh = check_reference_mesh(spec, redis)  # the upload reference.mesh_id names
    problem = check_calibration_spec(spec, settings, mesh)
    dumped = dump_spec(spec)
    digest = fem_hash(dumped)
    meta = records.get_fem_meta(redis, digest)
    pending = meta.get("status") in (FemStatus.QUEUED.value, FemStatus.RUNNING.value)
    supplied = supplied_reference(problem)
    started = (
        graph.submit_fem(redis, dumped, settings.job_options, supplied) if not pending else None
    )
    response.headers["Location"] = f"{router.prefix}/{digest}"
    if started is None:
        response.status_code = status.HTTP_200_OK
    return read(digest, redis)


@router.get("/{fem_id}", operation_id="get_fem_reference", responses=problem_responses(404, 422))
def read(
    fem_id: FemId,
    redis: RedisDep,
    arrays: Annotated[bool, Query(description="include nodes and displacements")] = True,
) -> FemReference:
    """Status, and once computed the nodal coordinates and displacements per load case."""
    meta = records.get_fem_meta(redis, fem_id)
    if not meta:
        raise ProblemError(404, "Not found", f"no FEM reference {fem_id!r}")
    out = FemReference(
        id=fem_id,
        status=FemStatus(meta["status"]),
        n_nodes=int(meta["n_nodes"]) if meta.get("n_nodes") else None,
        load_cases=json.loads(meta["load_cases"]) if meta.get("load_cases") else None,
        model=meta.get("model") or None,
        element=meta.get("element") or None,
        **(json.loads(meta["solver"]) if meta.get("solver") else {}),
        error=meta.get("error") or None,
    )
    if arrays and out.status == FemStatus.SUCCEEDED:
        data = records.get_fem_reference(redis, fem_id)
        if data is not None:
            out.nodes, out.displacements = data["nodes"], data["displacements"]
    return out
