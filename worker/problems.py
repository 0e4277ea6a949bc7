"""The problem a job works on: its stored spec built, with the uploaded mesh its regions need;
and its stored FEM reference.

A spec whose ``material.regions`` select by a cell tag of the uploaded mesh
``reference.mesh_id`` names (:func:`fpm.model.regions.tag_selectors`) is built with that mesh
from the store, so the lattice's cells and the FEM's elements take the regions the tags say;
every other spec is built from itself alone, without reading the mesh.
"""

from __future__ import annotations

from typing import Any

from redis import Redis

from fpm import load_problem
from fpm.fem.solution import FemResult
from fpm.model.problem import Problem
from fpm.model.regions import tag_selectors
from fpm.model.spec import ProblemSpec
from store import records


def problem_of(redis: Redis, spec: dict[str, Any]) -> Problem:
    """:func:`fpm.load_problem` of the stored ``spec`` (as the service dumped it), with the
    uploaded mesh when its regions select by tag. A spec stored before ``fpm.loads`` had
    ``"auto"`` has no ``loads`` (the dump left out its default, ``"node"``): it keeps ``"node"``,
    so a parameter set fitted then exports as it was fitted.

    Raises:
        LookupError: the mesh those regions read is no longer stored.
    """
    fpm = spec.get("fpm") or {}
    if "loads" not in fpm:  # dumped before fpm.loads 'auto' (the default since): it meant 'node'
        spec = {**spec, "fpm": {**fpm, "loads": "node"}}
    parsed = ProblemSpec.model_validate(spec)
    return load_problem(parsed, tagged_mesh(redis, parsed))


def tagged_mesh(redis: Redis, spec: ProblemSpec) -> dict[str, Any] | None:
    """The upload ``reference.mesh_id`` names (nodes, tetrahedra, tags) when the spec's regions
    select by its tags, else None (nothing read).

    Raises:
        LookupError: that mesh is not stored.
    """
    mesh_id = spec.reference.mesh_id
    if mesh_id is None or not tag_selectors(spec):
        return None
    mesh = records.get_mesh(redis, mesh_id)
    if mesh is None:
        raise LookupError(f"reference.mesh_id: no uploaded mesh {mesh_id}")
    return mesh


def reference_of(redis: Redis, fem_hash: str) -> FemResult | None:
    """The stored FEM reference ``fem_hash`` (read from its raw arrays), or None."""
    stored = records.get_fem_arrays(redis, fem_hash)
    return None if stored is None else FemResult.from_stored(*stored)
