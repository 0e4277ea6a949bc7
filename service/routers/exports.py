"""/v1/parameter-sets/{id}/export: a stored parameter set with its lattice, for other engines.

A parameter set holds the fitted numbers, not the lattice; its provenance names the calibration,
whose record keeps the validated spec (no expiry), and the FEM reference (no expiry). The
lattice is rebuilt from that spec, the FPM displacements (``vtu``) come from a run at the
parameters, the FEM's from the stored reference. Formats: :mod:`fpm.io.export`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query
from fastapi.responses import Response

from store import records

from ..deps import ParameterSetId, RedisDep
from ..errors import ProblemError, problem_responses
from .parameter_sets import stored_parameter_set

router = APIRouter(prefix="/v1/parameter-sets", tags=["parameter-sets"])

ExportFormat = Literal["json", "vtu", "sofa"]

CONTENT = {
    "application/json": {"schema": {"type": "object"}},
    "application/xml": {"schema": {"type": "string"}},
}


@router.get(
    "/{parameter_set_id}/export",
    operation_id="export_parameter_set",
    response_class=Response,
    responses={
        200: {
            "description": "json: nodes, springs [i, j, rest length, stiffness], masses, fixed "
            "nodes, d, dt, depth, perturbed layers per load case, with units; vtu: the lattice "
            "with FPM and FEM displacements and their error per load case (ParaView); sofa: a "
            "SOFA scene (.scn)",
            "content": CONTENT,
        },
        **problem_responses(404, 410, 422),
    },
)
def export(
    parameter_set_id: ParameterSetId,
    redis: RedisDep,
    fmt: Annotated[ExportFormat, Query(alias="format", description="json | vtu | sofa")] = "json",
) -> Response:
    """A stored parameter set with its lattice: ``json`` (any engine), ``vtu`` (ParaView) or
    ``sofa`` (a SOFA scene). 410 for a set stored by an older version, or whose calibration
    record (which holds the spec) is gone."""
    ps = stored_parameter_set(redis, parameter_set_id)
    provenance = ps.get("provenance") or {}
    record = records.get_calibration(redis, str(provenance.get("calibration_id", "")))
    if record is None or record.spec_hash != provenance.get("spec_hash"):
        raise ProblemError(
            410,
            "Gone",
            f"the calibration that holds the spec of parameter set {parameter_set_id} is gone: "
            "calibrate its spec again",
        )
    fem = None
    if fmt == "vtu":
        stored = records.get_fem_reference(redis, str(provenance.get("fem_hash", "")))
        fem = None if stored is None else stored["displacements"]
    from fpm.io.export import MEDIA_TYPES, SUFFIXES, export
    from fpm.model.problem import load_problem

    body = export(load_problem(record.spec), ps, fmt, fem=fem)  # a sync route: off the loop

    filename = f"{parameter_set_id}{SUFFIXES[fmt]}"
    return Response(
        content=body,
        media_type=MEDIA_TYPES[fmt],
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )
