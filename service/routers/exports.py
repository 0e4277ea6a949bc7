"""/v1/parameter-sets/{id}/export: a stored parameter set with its lattice, for other engines.

A parameter set holds the fitted numbers, not the lattice; its provenance names the calibration,
whose record keeps the validated spec (no expiry), and the FEM reference (no expiry). The
lattice is rebuilt from that spec, the FPM displacements (``vtu``) come from a run at the
parameters, the FEM's from the stored reference. Formats: :mod:`fpm.io.export`.

That takes the numerical kernels and up to seconds, so a worker makes the export, never this
process: the first request for a (parameter set, format) enqueues the export job
(:func:`store.graph.request_export`) and answers 202 ``pending`` with ``Retry-After``; once the
job has cached the bytes (:data:`store.scratch.EXPORT_TTL`), the answer is 200 with them.
"""

from __future__ import annotations

import gzip
from collections.abc import AsyncIterator
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from store import graph, scratch
from store.hashing import export_hash

from .. import worker_made
from ..deps import ParameterSetId, RedisDep, SettingsDep
from .parameter_sets import stored_parameter_set

router = APIRouter(prefix="/v1/parameter-sets", tags=["parameter-sets"])

ExportFormat = Literal["json", "vtu", "sofa", "sofa-python"]

MEDIA_TYPES = {
    "json": "application/json",
    "vtu": "application/xml",
    "sofa": "application/xml",
    "sofa-python": "text/x-python",
}
"""Each format's media type (those of :mod:`fpm.io.export`, which this process does not load)."""
SUFFIXES = {"json": ".json", "vtu": ".vtu", "sofa": ".scn", "sofa-python": ".py"}
"""Each format's file name suffix (:mod:`fpm.io.export`'s)."""

CONTENT = {
    "application/json": {"schema": {"type": "object"}},
    "application/xml": {"schema": {"type": "string"}},
    "text/x-python": {"schema": {"type": "string"}},
}


@router.get(
    "/{parameter_set_id}/export",
    operation_id="export_parameter_set",
    response_class=Response,
    responses=worker_made.responses(
        "export",
        {
            "description": "json: nodes, springs [i, j, rest length, stiffness], masses, fixed "
            "nodes, d, dt, depth, perturbed layers per load case, with units; vtu: the lattice "
            "with FPM and FEM displacements and their error per load case (ParaView); sofa: a "
            "SOFA scene (.scn, springs only); sofa-python: a SofaPython3 scene (.py) with the "
            "volume term as a Python ForceField",
            "content": CONTENT,
        },
    ),
)
def export(
    parameter_set_id: ParameterSetId,
    redis: RedisDep,
    settings: SettingsDep,
    request: Request,
    fmt: Annotated[
        ExportFormat, Query(alias="format", description="json | vtu | sofa | sofa-python")
    ] = "json",
) -> Response:
    """A stored parameter set with its lattice: ``json`` (any engine), ``vtu`` (ParaView) or
    ``sofa`` (a SOFA scene). A worker makes it: the first request answers 202 (``pending``,
    with Retry-After), ask again until 200. 410 for a set stored by an older version, or whose
    calibration record (which holds the spec) is gone; 503 with Retry-After when its export job
    failed (tried again after that); 422 when the parameters do not fit the spec's lattice."""
    ps = stored_parameter_set(redis, parameter_set_id)
    body = scratch.get_export(redis, export_hash(parameter_set_id, fmt))
    if body is None:
        made = worker_made.requested(
            redis,
            parameter_set_id,
            ps,
            lambda spec: graph.request_export(
                redis, parameter_set_id, fmt, spec, settings.finalize_timeout
            ),
            f"the export job of parameter set {parameter_set_id} as {fmt}",
            f"/v1/parameter-sets/{parameter_set_id}/export?format={fmt}",
        )
        if not isinstance(made, bytes):
            return made
        body = made
    # The cache holds the export gzip-compressed: sent as it is to a client that accepts gzip
    # (httpx, browsers, curl --compressed), unpacked here for one that does not.
    headers = {"Content-Disposition": f'attachment; filename="{parameter_set_id}{SUFFIXES[fmt]}"'}
    headers["Vary"] = "Accept-Encoding"
    if "gzip" not in request.headers.get("accept-encoding", ""):
        return Response(gzip.decompress(body), media_type=MEDIA_TYPES[fmt], headers=headers)
    headers["Content-Encoding"] = "gzip"
    headers["Content-Length"] = str(len(body))
    return StreamingResponse(_pieces(body), media_type=MEDIA_TYPES[fmt], headers=headers)


PIECE_BYTES = 1 << 18
"""An export goes out in pieces of this size (256 KiB), each written once the last has
drained: one 20 MB write would be copied whole into the event loop's send buffer, holding up
every other request for milliseconds (measured as the API's p99 while exports download)."""


async def _pieces(body: bytes) -> AsyncIterator[memoryview]:
    """``body`` in :data:`PIECE_BYTES` slices (views, not copies)."""
    view = memoryview(body)
    for start in range(0, len(view), PIECE_BYTES):
        yield view[start : start + PIECE_BYTES]
