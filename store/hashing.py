"""Content hashes: the identity of a spec and of the FEM reference it needs.

Both hash the canonical JSON (sorted keys, no whitespace) of the spec *after* validation with
every default filled in, so two specs that differ only in spelt-out defaults are the same.
"""

import hashlib
import json
from typing import Any

from fpm.model.spec import EXPORT_VERSION, FEM_VERSION, MODEL_VERSION

FEM_FIELDS = ("geometry", "material", "fixed", "load_cases")
"""The spec fields the FEM reference depends on."""

RECORD_VERSION = 2
"""Layout of the results and parameter sets the worker writes (2: two-stage fields, relative
discrepancy, family stiffnesses). Part of the spec hash like fpm's MODEL_VERSION, so that a
resubmitted spec is not answered with a record of the older layout."""


def canonical(data: Any) -> bytes:
    """Canonical JSON bytes of ``data``."""
    return json.dumps(data, sort_keys=True, separators=(",", ":")).encode()


def spec_hash(spec: dict[str, Any]) -> str:
    """sha256 of the whole validated spec (a dumped :class:`fpm.model.spec.ProblemSpec`), of
    :data:`fpm.model.spec.MODEL_VERSION` and of :data:`RECORD_VERSION`, so results of older numerics
    or in an older layout are not handed out again."""
    identity = {"model": MODEL_VERSION, "record": RECORD_VERSION, "spec": spec}
    return hashlib.sha256(canonical(identity)).hexdigest()


def fem_spec(spec: dict[str, Any]) -> dict[str, Any]:
    """The part of ``spec`` the FEM reference depends on (itself a loadable spec): geometry,
    material, fixed nodes, load cases and validation cases (when there are any, so a spec
    without them keeps its identity), the reference's ``integration`` (and its supplied
    ``displacements``, or its tetrahedral ``mesh`` or ``mesh_id``, if any; its ``refine`` and
    ``node_budget`` when given), and ``fpm.gravity``
    when it is set (the FEM then carries the solid's weight)."""
    out = {name: spec[name] for name in FEM_FIELDS}
    if spec.get("validation_cases"):  # solved with the load cases, after them
        out["validation_cases"] = spec["validation_cases"]
    reference = spec.get("reference") or {}
    out["reference"] = {"integration": reference.get("integration", "selective")}
    if reference.get("displacements") is not None:  # a supplied reference: its own identity
        out["reference"]["displacements"] = reference["displacements"]
    for name in ("mesh", "mesh_id"):  # the tetrahedral reference's mesh (the id is its sha256)
        if reference.get(name) is not None:
            out["reference"][name] = reference[name]
    for name in ("refine", "node_budget"):  # the refinement asked for (fpm.fem.refine)
        if reference.get(name) is not None:
            out["reference"][name] = reference[name]
    gravity = (spec.get("fpm") or {}).get("gravity")
    if gravity is not None and any(gravity):
        out["fpm"] = {"gravity": list(gravity)}
    return out


def fem_hash(spec: dict[str, Any]) -> str:
    """sha256 of :func:`fem_spec` (geometry, material, fixed, load cases, integration,
    gravity) and of :data:`fpm.model.spec.FEM_VERSION`: the FEM reference's identity."""
    identity = {"fem": FEM_VERSION, "spec": fem_spec(spec)}
    return hashlib.sha256(canonical(identity)).hexdigest()


DAMPING_ONLY = ("dt", "max_steps", "settle_distance", "settle_tolerance", "auto_depth_tolerance")
"""Two-stage: the ``fpm`` settings that only the damping stage reads (stage 1's chains fit the
stiffness on static equilibria), with ``annealing.bounds.d``: a change in them keeps stage 1's
chains (:func:`stiffness_spec`)."""


def stiffness_spec(spec: dict[str, Any]) -> dict[str, Any]:
    """The part of ``spec`` stage 1's chains depend on besides their reference: all of it but
    its name and validation cases and, two-stage, :data:`DAMPING_ONLY` (the paper method
    anneals d with the stiffness: all of it)."""
    kept = {k: v for k, v in spec.items() if k not in ("name", "validation_cases")}
    if spec["annealing"]["method"] != "two-stage":
        return kept
    fpm = {k: v for k, v in spec["fpm"].items() if k not in DAMPING_ONLY}
    bounds = {k: v for k, v in (spec["annealing"].get("bounds") or {}).items() if k != "d"}
    return kept | {"fpm": fpm, "annealing": spec["annealing"] | {"bounds": bounds}}


def stiffness_hash(spec: dict[str, Any]) -> str:
    """sha256 of :func:`stiffness_spec`, of the FEM reference's identity (:func:`fem_hash`) and
    of :data:`fpm.model.spec.MODEL_VERSION`: the identity of stage 1's chains, which a
    calibration of a spec differing only in damping settings, or one run again after a
    failure, takes as they are."""
    identity = {"model": MODEL_VERSION, "fem": fem_hash(spec), "spec": stiffness_spec(spec)}
    return hashlib.sha256(canonical(identity)).hexdigest()


def export_hash(parameter_set_id: str, fmt: str) -> str:
    """sha256 of a parameter set id, an export format and
    :data:`fpm.model.spec.EXPORT_VERSION`: the identity of a cached export.

    The id stands for the content: it derives from the spec hash (which covers the spec,
    MODEL_VERSION and RECORD_VERSION), the set is written once (SET NX) and the spec and FEM
    reference it is exported with are stored under that same spec hash and the set's FEM hash,
    neither ever rewritten. The export version covers the code that writes the formats."""
    identity = {"export": EXPORT_VERSION, "format": fmt, "parameter_set": parameter_set_id}
    return hashlib.sha256(canonical(identity)).hexdigest()


VIEW_VERSION = 1
"""Layout of a parameter set's 3D view data (``worker/view.py``): bump it when a change there
alters the bytes, so that cached views of the older layout are not handed out."""


def view_hash(parameter_set_id: str) -> str:
    """sha256 of a parameter set id and :data:`VIEW_VERSION`: the identity of its cached 3D view
    data (the id stands for the content, as in :func:`export_hash`)."""
    identity = {"parameter_set": parameter_set_id, "view": VIEW_VERSION}
    return hashlib.sha256(canonical(identity)).hexdigest()


def canonical_mesh(nodes: Any, tetrahedra: Any) -> dict[str, Any]:
    """A tetrahedral mesh in one spelling: nodes as lists of floats (m), tetrahedra as lists of
    ints, so that ``0`` and ``0.0`` name the same mesh."""
    return {
        "nodes": [[float(x) for x in node] for node in nodes],
        "tetrahedra": [[int(i) for i in tet] for tet in tetrahedra],
    }


def mesh_hash(mesh: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of :func:`canonical_mesh`: an uploaded mesh's id."""
    return hashlib.sha256(canonical(mesh)).hexdigest()
