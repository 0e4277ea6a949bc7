"""Configured limits: request body size (ASGI middleware) and problem size (spec checks).

Both run before anything is built or written, so an oversized request costs little and
leaves nothing behind.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from redis import Redis
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from fpm import Problem, ProblemSpec, load_problem
from fpm.limits import LimitError, Limits, check_size
from fpm.model.regions import tag_selectors
from fpm.model.spec import NetworkGeometry
from fpm.model.support import unheld_reason
from fpm.model.tetrahedra import check_tetrahedra, lattice_pieces
from store import records
from store.text import refusal

from .errors import MEDIA_TYPE, ProblemError
from .settings import Settings


class BodySizeLimit:
    """Answer 413 to a request whose body exceeds ``max_bytes`` (declared or streamed)."""

    def __init__(self, app: ASGIApp, max_bytes: int, per_path: dict[str, int] | None = None):
        """``per_path``: other limits for requests to exactly these paths (the mesh upload)."""
        self.app = app
        self.max_bytes = max_bytes
        self.per_path = per_path or {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.per_path.get(scope.get("path", ""), self.max_bytes)
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._reject(send, limit)
            return
        received = 0
        too_large = False

        async def counting_receive() -> Message:
            nonlocal received, too_large
            message = await receive()
            received += len(message.get("body", b""))
            if received > limit:
                too_large = True
                raise _TooLarge
            return message

        async def guarded_send(message: Message) -> None:
            # The body parser may turn _TooLarge into an answer of its own (400): drop it.
            if not too_large:
                await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except _TooLarge:
            pass
        if too_large:
            await self._reject(send, limit)

    async def _reject(self, send: Send, limit: int) -> None:
        body = json.dumps(
            {
                "type": "about:blank",
                "title": "Request body too large",
                "status": 413,
                "detail": f"the request body exceeds the limit of {limit} bytes",
            }
        ).encode()
        headers = [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", b"%d" % len(body))]
        await send({"type": "http.response.start", "status": 413, "headers": headers})
        await send({"type": "http.response.body", "body": body})


class _TooLarge(Exception):
    pass


def _invalid(errors: list[dict[str, str]]) -> ProblemError:
    detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
    return ProblemError(422, "Invalid input", detail, errors=errors)


def _rejected(field: str, message: str) -> ProblemError:
    return _invalid([{"field": field, "message": message}])


def size_limits(settings: Settings) -> Limits:
    """The service's size limits (:mod:`fpm.limits`, as ``fpmcal`` applies them)."""
    return Limits(
        max_nodes=settings.max_nodes,
        max_load_cases=settings.max_load_cases,
        max_chains=settings.max_chains,
        max_mesh_tetrahedra=settings.max_mesh_tetrahedra,
    )


def text_refusals(data: Any) -> list[dict[str, str]]:
    """[{field, message}] for every string in ``data`` (a dumped spec) that free text may not
    hold (:func:`store.text.refusal`: control characters, lone surrogates, line separators).

    Every string is checked, so a free-text field added to the spec later is covered too
    (fixed choices such as ``face`` hold no such character anyway). Numbers are skipped
    without a call: a mesh of 80 000 nodes takes well under 0.1 s.
    """
    out: list[dict[str, str]] = []

    def walk(value: Any, field: str) -> None:
        if isinstance(value, str):
            why = refusal(value)
            if why is not None:
                out.append({"field": field or "body", "message": why})
            return
        items = value.items() if isinstance(value, dict) else enumerate(value)
        for key, item in items:
            if isinstance(item, str | dict | list | tuple):
                walk(item, f"{field}.{key}" if field else str(key))

    walk(data, "")
    return out


def check_calibration_spec(
    spec: ProblemSpec, settings: Settings, mesh: dict[str, Any] | None = None
) -> Problem:
    """Check ``spec``'s text and its size against the limits, then build it
    (:func:`fpm.load_problem`; ``mesh`` the upload ``reference.mesh_id`` names,
    :func:`check_reference_mesh`: the spec is built with it when its regions select by its
    tags), then check that its reference mesh is one solid where the lattice is
    (:func:`check_reference_pieces`).

    Raises:
        ProblemError: 422 naming the field with refused characters, over a limit or that
            cannot be calibrated.
        pydantic.ValidationError: a spec that does not fit its own solid (answered 422).
    """
    refused = text_refusals(spec.model_dump())
    if refused:
        raise _invalid(refused)
    if isinstance(spec.geometry, NetworkGeometry):
        raise _rejected(
            "geometry.type", "a network has no FEM reference, so it cannot be calibrated"
        )
    try:
        check_size(spec, size_limits(settings))
    except LimitError as e:
        raise _rejected(e.field, e.message) from None
    problem = load_problem(spec, mesh if tag_selectors(spec) else None)
    if not problem.fixed.any():
        raise _rejected("fixed", "selects no node: the FEM reference needs the solid held")
    hexahedra = problem.solid.elements()
    assert hexahedra is not None  # networks were refused above
    reason = unheld_reason(
        problem.nodes, hexahedra, problem.fixed, one_block=problem.solid.shape is not None
    )
    if reason:  # refused now rather than failed in a worker
        raise _rejected("fixed", reason)
    check_reference_pieces(problem, mesh)
    return problem


def check_reference_pieces(problem: Problem, mesh: dict[str, Any] | None) -> None:
    """The FEM reference's tetrahedra (``reference.mesh``, or ``mesh``: the upload
    ``reference.mesh_id`` names) must not be pieces without shared faces that the lattice's
    cells join into one solid (:func:`fpm.model.tetrahedra.lattice_pieces`, as
    ``spec_from_mesh`` refuses them): the FEM would hold and load them apart (a piece not held
    leaves the stiffness matrix singular). Nodes numbered twice at one point need no check:
    the pieces are joined by position, and the FEM joins such nodes
    (:func:`fpm.model.tetrahedra.merge_coincident`). A supplied reference solves no FEM.

    Raises:
        ProblemError: 422 at ``reference.mesh`` or ``reference.mesh_id`` naming the piece (a
            tetrahedron of it, its size, its centre).
    """
    reference = problem.spec.reference
    if reference.displacements is not None:
        return
    if reference.mesh is not None:
        field, nodes, tets = "reference.mesh", reference.mesh.nodes, reference.mesh.tetrahedra
    elif reference.mesh_id is not None and mesh is not None:
        field, nodes, tets = "reference.mesh_id", mesh["nodes"], mesh["tetrahedra"]
    else:
        return
    hexahedra = problem.solid.elements()
    if hexahedra is None or not len(hexahedra):
        return
    x, t = np.asarray(nodes, dtype=float), np.asarray(tets, dtype=np.int64)
    apart = lattice_pieces(x, t, problem.nodes[hexahedra].mean(axis=1)).joined_apart(x, t)
    if apart:
        raise _rejected(field, apart)


def check_reference_mesh(spec: ProblemSpec, redis: Redis) -> dict[str, Any] | None:
    """A spec naming ``reference.mesh_id`` must name a mesh uploaded with ``POST /v1/meshes``.
    Returns that mesh (nodes, tetrahedra, tags), else None (no ``mesh_id``): the spec is built
    with it when its material regions select by its tags
    (:func:`fpm.model.regions.tag_selectors`), and its pieces are checked against the lattice
    (:func:`check_reference_pieces`).

    Raises:
        ProblemError: 422 at ``reference.mesh_id`` when no such mesh is stored.
    """
    mesh_id = spec.reference.mesh_id
    if mesh_id is None:
        return None
    mesh = records.get_mesh(redis, mesh_id)
    if mesh is None:
        raise _rejected(
            "reference.mesh_id",
            f"no uploaded mesh {mesh_id}: upload it first (POST /v1/meshes returns its id)",
        )
    return mesh


def mesh_refusals(nodes: Any, tetrahedra: Any, settings: Settings) -> list[dict[str, str]]:
    """[{field, message}] for an uploaded mesh over the limits or not usable as a reference
    (:func:`fpm.model.tetrahedra.check_tetrahedra`: the element named); empty when fine."""
    if len(tetrahedra) > settings.max_mesh_tetrahedra:
        return [
            {
                "field": "tetrahedra",
                "message": f"{len(tetrahedra)} tetrahedra is over the limit of "
                f"{settings.max_mesh_tetrahedra}",
            }
        ]
    found = check_tetrahedra(np.asarray(nodes, dtype=float), np.asarray(tetrahedra, dtype=np.int64))
    return [
        {"field": field if index is None else f"{field}.{index}", "message": message}
        for field, index, message in found
    ]


def mesh_rejection(refusals: list[dict[str, str]]) -> ProblemError:
    """The 422 of :func:`mesh_refusals`."""
    return _invalid(refusals)


def dump_spec(spec: ProblemSpec) -> dict[str, Any]:
    """The validated spec with every default filled in (what jobs and hashes see)."""
    return spec.model_dump(mode="json")


def supplied_reference(problem: Problem) -> dict[str, Any] | None:
    """The spec's ``reference.displacements`` in the stored FemResult layout (model and method
    ``"supplied"``), or None when it supplies none; its shape was checked by
    :func:`fpm.load_problem`."""
    displacements = problem.spec.reference.displacements
    if displacements is None:
        return None
    names = [case.name for case in problem.load_cases]
    return {
        "nodes": problem.nodes.tolist(),
        "displacements": [[list(u) for u in case] for case in displacements],
        "residuals": [0.0] * len(names),
        "load_cases": names,
        "method": "supplied",
        "model": "supplied",
        "load_steps": [],
        "newton_iterations": [],
    }
