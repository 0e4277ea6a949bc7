"""/v1/parameter-sets/{id}/view: the data of a stored parameter set's 3D view (the web view).

The lattice's outer surface, and per load case (fitted, then validation) the FEM's and the
settled FPM's displacements at its nodes, the fixed and the loaded nodes, and the fit figures:
one compact binary body (a small JSON header and little-endian float32/uint32 arrays; the
layout is documented in ``worker/view.py``), sent gzip-compressed.

It needs FPM runs at the set's parameters, so a worker makes it, never this process, exactly as
an export is made (:mod:`.exports`): the first request enqueues the view job
(:func:`store.graph.request_view`) and answers 202 ``pending`` with ``Retry-After``; once the job
has cached the bytes (a day, :data:`store.scratch.EXPORT_TTL`), the answer is 200 with them. A
view whose cached bytes expired is made again the same way.
"""

from __future__ import annotations

import gzip

from fastapi import APIRouter, Request
from fastapi.responses import Response

from store import graph, scratch
from store.hashing import view_hash

from .. import worker_made
from ..deps import ParameterSetId, RedisDep, SettingsDep
from .parameter_sets import stored_parameter_set

router = APIRouter(prefix="/v1/parameter-sets", tags=["parameter-sets"])

MEDIA_TYPE = "application/octet-stream"
"""The view body's media type: binary (``FPMV``, a JSON header, typed arrays)."""


@router.get(
    "/{parameter_set_id}/view",
    operation_id="get_parameter_set_view",
    response_class=Response,
    responses=worker_made.responses(
        "3D view",
        {
            "description": "the 3D view data: b'FPMV', a little-endian uint32 header length, "
            "the header (JSON: h, node counts, bounds, per case its name, kind, figures and "
            "the names of its arrays; each array's dtype, shape and byte offset), then the "
            "arrays (float32 / uint32, little-endian): surface vertex positions, triangles, "
            "the vertices' lattice nodes, fixed vertices, and per case FEM and FPM "
            "displacements, loaded vertices and their forces",
            "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
    ),
)
def view(
    parameter_set_id: ParameterSetId, redis: RedisDep, settings: SettingsDep, request: Request
) -> Response:
    """The data of a stored parameter set's 3D view: its lattice's outer surface and, per load
    case (fitted, then validation), the FEM reference's and the settled FPM's displacements,
    the fixed and loaded nodes and the fit figures, as one binary body (gzip-compressed). A
    worker makes it: the first request answers 202 (``pending``, with Retry-After), ask again
    until 200. 410 for a set stored by an older version, or whose calibration record is gone;
    503 with Retry-After when its job failed (tried again after that); 422 when the
    parameters do not fit the spec's lattice."""
    ps = stored_parameter_set(redis, parameter_set_id)
    body = scratch.get_export(redis, view_hash(parameter_set_id))
    if body is None:
        made = worker_made.requested(
            redis,
            parameter_set_id,
            ps,
            lambda spec: graph.request_view(
                redis, parameter_set_id, spec, settings.finalize_timeout
            ),
            f"the 3D view job of parameter set {parameter_set_id}",
            f"/v1/parameter-sets/{parameter_set_id}/view",
        )
        if not isinstance(made, bytes):
            return made
        body = made
    # Cached gzip-compressed: sent as it is to a client that accepts gzip (browsers, httpx),
    # unpacked here for one that does not.
    headers = {"Vary": "Accept-Encoding", "Cache-Control": "no-cache"}
    if "gzip" not in request.headers.get("accept-encoding", ""):
        return Response(gzip.decompress(body), media_type=MEDIA_TYPE, headers=headers)
    headers["Content-Encoding"] = "gzip"
    return Response(body, media_type=MEDIA_TYPE, headers=headers)
