"""/v1/meshes: upload a tetrahedral mesh for FEM references (``reference.mesh_id``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Response, status
from pydantic import BaseModel

from fpm.model.spec import ReferenceMesh
from store import records
from store.hashing import canonical_mesh, mesh_hash

from ..deps import RedisDep, SettingsDep
from ..errors import problem_responses
from ..limits import mesh_refusals, mesh_rejection

router = APIRouter(prefix="/v1/meshes", tags=["meshes"])


class MeshId(BaseModel):
    """An uploaded mesh's id: the sha256 of its canonical JSON; name it in a spec's
    ``reference.mesh_id``."""

    id: str


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    operation_id="upload_mesh",
    responses={
        200: {"model": MeshId, "description": "the same mesh was uploaded before"},
        **problem_responses(400, 413, 422),
    },
)
def upload(
    mesh: Annotated[ReferenceMesh, Body()],
    redis: RedisDep,
    settings: SettingsDep,
    response: Response,
) -> MeshId:
    """Store a tetrahedral mesh ``{"nodes": [[x, y, z], ...], "tetrahedra": [[i, j, k, l],
    ...]}`` (m, 0-based, positive volumes) for the FEM reference of specs that name it in
    ``reference.mesh_id``: the reference is then solved on it with 10-node tetrahedra and
    read at the lattice nodes. ``"tags"``, one integer per tetrahedron (cell data), are kept
    with it and are part of its id.

    Content-addressed and kept without expiry: 201 with the id when new, 200 with the same id
    when it was uploaded before. A mesh with an index out of range, a repeated corner, an
    inverted or a degenerate tetrahedron is refused with 422 naming the element
    (``tetrahedra.<i>``), and nothing is stored. The body may be larger than a spec's
    (``max_mesh_bytes``). Nodes at one point numbered twice are kept as sent (the id is of the
    mesh sent) and joined by the FEM; pieces not joined through shared faces that a spec's
    lattice joins into one solid are refused when the spec is submitted (422 at
    ``reference.mesh_id`` naming one).
    """
    refused = mesh_refusals(mesh.nodes, mesh.tetrahedra, settings)
    if refused:
        raise mesh_rejection(refused)
    data = canonical_mesh(mesh.nodes, mesh.tetrahedra)
    if mesh.tags is not None:  # cell data for material.regions selectors: part of the identity
        data["tags"] = [int(t) for t in mesh.tags]
    digest = mesh_hash(data)
    if not records.save_mesh(redis, digest, data):
        response.status_code = status.HTTP_200_OK
    return MeshId(id=digest)
