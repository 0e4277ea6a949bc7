"""The 3D view of a stored parameter set, as data: the web view's 3D page draws it with three.js.

One body per parameter set, made by a worker (the service never loads the kernels) and cached
like an export (:func:`store.graph.request_view`, ``GET /v1/parameter-sets/{id}/view``):

- the lattice's outer surface: the faces of the hexahedra that belong to exactly one
  hexahedron, each split into two triangles, over the surface nodes only, renumbered
  (:func:`surface_quads`);
- per load case (the fitted ones, then the validation cases): the FEM reference's displacements
  (from the stored reference, which holds the load cases then the validation cases) and the
  FPM's settled displacements at the set's parameters (:func:`fpm.model.stiffness.fitted_theta`):
  for a fitted case the run from rest the result's figures come from (:func:`fpm.simulate` at
  the set's d, depth and dt), for a validation case its static equilibrium, as the validation
  figures are made (:func:`fpm.fitting.damping.validation.validate`);
- the fixed nodes, and per case the loaded nodes with their forces, and the figures the set
  already holds (relative discrepancy first).

The layout (:data:`MAGIC`, then a little-endian uint32 header length, the header as UTF-8
JSON padded with spaces to a multiple of 4 bytes, then the arrays, little-endian, each at the
offset its header entry gives from the start of the body, a multiple of 4)::

    {"format": "fpm-view", "version": 1, "parameter_set_id", "name", "h", "nodes",
     "vertices", "surface_vertices", "triangles", "bounds": [[x0, y0, z0], [x1, y1, z1]],
     "gravity": [gx, gy, gz] (the spec's fpm.gravity, m/s^2: the page's up axis), "units": {...},
     "arrays": {name: {"dtype": "float32" | "uint32", "shape": [...], "offset": bytes}},
     "cases": [{"name", "kind": "fitted" | "validation", "relative_discrepancy",
                "loaded_discrepancy" (fitted only), "discrepancy_h", "fem_max",
                "discrepancy_max", "settled", "steps", "arrays": {"fem", "fpm", "loaded",
                "forces"}}]}

Vertices are lattice nodes: the surface nodes first (``surface_vertices`` of them, the only
ones the triangles use), then the fixed and loaded nodes off the surface, so that every marked
node has a position; ``node_index`` gives each vertex's lattice node. ``fem`` and ``fpm`` are
(vertices, 3) displacements, m; ``fem_max`` is the case's largest FEM displacement and
``discrepancy_max`` its largest |p_i - q_i|, both over every node, m.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np
from rq import get_current_job

from fpm import simulate
from fpm.dynamics.equilibrium import static_equilibrium
from fpm.model.problem import Problem
from fpm.model.stiffness import fitted_theta
from store import records, scratch
from store.hashing import VIEW_VERSION, view_hash

from .problems import problem_of, reference_of

MAGIC = b"FPMV"
"""The first 4 bytes of a view body."""

FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]],
    dtype=np.int64,
)
"""The 6 faces of a hexahedron in :mod:`fpm.model.hexahedron`'s node order, each counter-
clockwise seen from outside a positively oriented hexahedron (its normal points out)."""


class ViewError(ValueError):
    """The parameter set does not fit its spec's lattice (the same input fails again)."""


FACE_LOCAL = np.array([4, 5, 2, 1, 3, 0])
"""Each row of :data:`FACES` as a local face of :func:`fpm.model.geometry.boundary_faces`
(``2 * axis + (side > 0)``)."""


def surface_quads(hexahedra: np.ndarray) -> np.ndarray:
    """(F, 4) the faces of ``hexahedra`` (H, 8) on the lattice's surface (of one hexahedron
    only, holes and cavities included; a graded lattice's interfaces excepted:
    :func:`fpm.model.geometry.boundary_faces`), in :data:`FACES`' orientation."""
    from fpm.model.geometry import boundary_faces

    hexahedra = np.asarray(hexahedra, dtype=np.int64)
    quads = hexahedra[:, FACES].reshape(-1, 4)
    if not len(quads):
        return quads
    return quads[boundary_faces(hexahedra)[:, FACE_LOCAL].ravel()]


def triangles_of(quads: np.ndarray) -> np.ndarray:
    """(2F, 3) two triangles per quad (a, b, c, d): (a, b, c) and (a, c, d), same orientation."""
    quads = np.asarray(quads)
    return np.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)


def view_cases(
    problem: Problem, parameters: dict[str, Any], reference: Any, full_depth: int | None
) -> list[dict[str, Any]]:
    """Per case, fitted then validation: name, kind, ``fem`` and ``fpm`` (N, 3) displacements,
    m, ``loaded`` nodes with their ``forces`` (N), and the settle ``steps`` (fitted) and
    ``settled`` (fitted: the run settled; validation: the static solve converged).

    Args:
        problem: the spec's problem.
        parameters: a parameter set (or calibration result): stiffness, d (or damping), depth,
            and dt (else the spec's).
        reference: (L + V, N, 3) FEM displacements, m (V may be 0: the validation cases are
            then left out).
        full_depth: the load cases' deepest perturbed list (the result's ``full_depth``): a
            validation case is solved over every layer when the depth reaches it, as the
            validation figures are.
    """
    try:
        theta = fitted_theta(problem, parameters)
        d = float(parameters["d"] if "d" in parameters else parameters["damping"])
        depth = int(parameters["depth"])
    except (KeyError, TypeError, ValueError) as e:
        raise ViewError(f"the parameters do not fit the spec: {e}") from None
    dt = parameters.get("dt")
    every = np.asarray(reference, dtype=float)
    n_cases, n_checks = len(problem.load_cases), len(problem.validation_cases)
    if every.ndim != 3 or every.shape[1:] != (problem.n_nodes, 3) or len(every) < n_cases:
        raise ViewError(
            f"the FEM reference has shape {every.shape}, the spec's lattice needs "
            f"({n_cases} (+ {n_checks}), {problem.n_nodes}, 3)"
        )
    cases = []
    for j, case in enumerate(problem.load_cases):
        run = simulate(problem, k=theta, d=d, depth=depth, load_case=j, dt=dt)
        cases.append(
            {
                "name": case.name,
                "kind": "fitted",
                "fem": every[j],
                "fpm": run.displacements,
                "loaded": case.nodes,
                "forces": case.forces,
                "steps": int(run.steps),
                "settled": bool(run.settled),
            }
        )
    if n_checks and len(every) >= n_cases + n_checks:
        checked = problem.validation_problem()
        layers = depth if full_depth is None or depth < full_depth else problem.n_nodes
        for v, case in enumerate(checked.load_cases):
            solved = static_equilibrium(checked, k=theta, depth=layers, load_case=v)
            cases.append(
                {
                    "name": case.name,
                    "kind": "validation",
                    "fem": every[n_cases + v],
                    "fpm": solved.displacements,
                    "loaded": case.nodes,
                    "forces": case.forces,
                    "steps": None,
                    "settled": bool(solved.converged),
                }
            )
    return cases


def view_body(
    problem: Problem,
    parameters: dict[str, Any],
    reference: Any,
    *,
    parameter_set_id: str = "",
    full_depth: int | None = None,
) -> bytes:
    """The view's bytes (the module's layout) of ``problem`` at ``parameters`` (a parameter
    set) against ``reference`` ((L + V, N, 3) FEM displacements, m)."""
    hexahedra = problem.solid.elements()
    if hexahedra is None:
        raise ViewError("a network geometry has no hexahedra, so no surface to draw")
    nodes = problem.nodes
    if isinstance(parameters.get("geometry"), dict):
        count = parameters["geometry"].get("nodes")
        if isinstance(count, int) and count != problem.n_nodes:
            raise ViewError(
                f"the parameters were fitted on {count} nodes; the spec builds {problem.n_nodes}"
            )
    cases = view_cases(problem, parameters, reference, full_depth)
    quads = surface_quads(hexahedra)
    on_surface = np.unique(quads)
    marked = np.unique(
        np.concatenate(
            [np.flatnonzero(problem.fixed), *(np.asarray(c["loaded"]) for c in cases)]
        ).astype(np.int64)
    )
    extra = np.setdiff1d(marked, on_surface, assume_unique=True)
    vertex_nodes = np.concatenate([on_surface, extra])
    vertex_of = np.full(problem.n_nodes, -1, dtype=np.int64)
    vertex_of[vertex_nodes] = np.arange(len(vertex_nodes))

    arrays: dict[str, np.ndarray] = {
        "positions": nodes[vertex_nodes].astype("<f4"),
        "triangles": vertex_of[triangles_of(quads)].astype("<u4"),
        "node_index": vertex_nodes.astype("<u4"),
        "fixed": vertex_of[np.flatnonzero(problem.fixed)].astype("<u4"),
    }
    fitted = {
        "relative_discrepancy": list(parameters.get("relative_discrepancy") or []),
        "loaded_discrepancy": list(parameters.get("loaded_discrepancy") or []),
        "discrepancy_h": list(parameters.get("discrepancy_h") or []),
    }
    checks = {
        "relative_discrepancy": list(parameters.get("validation_relative_discrepancy") or []),
        "discrepancy_h": list(parameters.get("validation_discrepancy_h") or []),
    }
    headers = []
    for i, case in enumerate(cases):
        p, q = np.asarray(case["fpm"], dtype=float), np.asarray(case["fem"], dtype=float)
        validation = case["kind"] == "validation"
        j = i - len(problem.load_cases) if validation else i
        figures = checks if validation else fitted
        names = {part: f"case{i}.{part}" for part in ("fem", "fpm", "loaded", "forces")}
        arrays[names["fem"]] = q[vertex_nodes].astype("<f4")
        arrays[names["fpm"]] = p[vertex_nodes].astype("<f4")
        arrays[names["loaded"]] = vertex_of[np.asarray(case["loaded"])].astype("<u4")
        arrays[names["forces"]] = np.asarray(case["forces"], dtype=float).astype("<f4")
        headers.append(
            {
                "name": case["name"],
                "kind": case["kind"],
                **{
                    name: (values[j] if j < len(values) else None)
                    for name, values in figures.items()
                },
                **({"loaded_discrepancy": None} if validation else {}),
                "fem_max": float(np.linalg.norm(q, axis=1).max(initial=0.0)),
                "discrepancy_max": float(np.linalg.norm(p - q, axis=1).max(initial=0.0)),
                "steps": case["steps"],
                "settled": case["settled"],
                "arrays": names,
            }
        )
    header = {
        "format": "fpm-view",
        "version": VIEW_VERSION,
        "parameter_set_id": parameter_set_id,
        "name": problem.spec.name,
        "h": problem.h,
        "nodes": problem.n_nodes,
        "vertices": len(vertex_nodes),
        "surface_vertices": len(on_surface),
        "triangles": 2 * len(quads),
        "bounds": [nodes.min(axis=0).tolist(), nodes.max(axis=0).tolist()],
        "gravity": [float(g) for g in problem.spec.fpm.gravity],
        "units": {
            "positions": "m",
            "displacements": "m",
            "forces": "N",
            "discrepancy": "%",
            "indices": "vertices (node_index: lattice nodes)",
        },
        "arrays": {},
        "cases": headers,
    }
    return pack(header, arrays)


def pack(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    """:data:`MAGIC`, the header's length, the header (with each array's dtype, shape and
    offset filled in) and the arrays, each 4-byte aligned."""
    offset = 0
    offsets = {}
    for name, array in arrays.items():
        offsets[name] = offset
        offset += -(-array.nbytes // 4) * 4
    # Offsets from the start of the body: the header's own length shifts them, and the
    # length's digits depend on the offsets, so settle it in a few rounds.
    start = 0
    for _ in range(8):
        header["arrays"] = {
            name: {
                "dtype": array.dtype.name,
                "shape": list(array.shape),
                "offset": offsets[name] + start,
            }
            for name, array in arrays.items()
        }
        text = json.dumps(header, separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        if 8 + len(text) == start:
            break
        start = 8 + len(text)
    else:  # pragma: no cover - the offsets' digits converge in two or three rounds
        raise RuntimeError("the view header's length did not settle")
    pieces = [MAGIC, struct.pack("<I", len(text)), text]
    for array in arrays.values():
        raw = np.ascontiguousarray(array).tobytes()
        pieces.append(raw + b"\0" * (-len(raw) % 4))
    return b"".join(pieces)


def unpack(body: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and the arrays of a view body (what the web view's script decodes)."""
    if body[:4] != MAGIC:
        raise ValueError("not a view body")
    (length,) = struct.unpack("<I", body[4:8])
    header = json.loads(body[8 : 8 + length])
    arrays = {}
    for name, entry in header["arrays"].items():
        dtype = np.dtype(entry["dtype"]).newbyteorder("<")
        count = int(np.prod(entry["shape"], dtype=np.int64))
        flat = np.frombuffer(body, dtype=dtype, count=count, offset=entry["offset"])
        arrays[name] = flat.reshape(entry["shape"])
    return header, arrays


def parameter_set_view(parameter_set_id: str) -> dict[str, Any]:
    """RQ job: make and cache the 3D view data of a stored parameter set, which the service
    hands out (:func:`store.graph.request_view`).

    The lattice is rebuilt from the spec in the calibration record the set's provenance names,
    the FEM displacements come from the stored reference. A failure is stored, not raised, for
    the cool-down (:data:`store.scratch.EXPORT_FAILED_TTL`), as the export job does: ``invalid``
    when the parameters do not fit the lattice (:class:`ViewError`). Returns a summary.
    """
    job = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    redis = job.connection
    digest = view_hash(parameter_set_id)
    if scratch.has_export(redis, digest):
        return {"skipped": True}
    ps = records.get_parameter_set(redis, parameter_set_id)
    provenance = (ps or {}).get("provenance") or {}
    record = records.get_calibration(redis, str(provenance.get("calibration_id", "")))
    invalid = False
    try:
        if ps is None:
            raise LookupError(f"no parameter set {parameter_set_id!r}")
        if record is None or record.spec_hash != provenance.get("spec_hash"):
            raise LookupError("the calibration that holds the parameter set's spec is gone")
        stored = reference_of(redis, str(provenance.get("fem_hash", "")))
        if stored is None:
            raise LookupError("the parameter set's FEM reference is no longer stored")
        full_depth = (record.result or {}).get("full_depth")
        body = view_body(
            problem_of(redis, record.spec),
            ps,
            stored.displacements,
            parameter_set_id=parameter_set_id,
            full_depth=None if full_depth is None else int(full_depth),
        )
    except ViewError as e:
        error, invalid = str(e), True
    except Exception as e:  # stored and shown; tried again after the cool-down
        error = f"{type(e).__name__}: {e}"
    else:
        scratch.save_export(redis, digest, body)
        return {"bytes": len(body)}
    scratch.save_export_failure(redis, digest, error, invalid)
    return {"failed": error}
