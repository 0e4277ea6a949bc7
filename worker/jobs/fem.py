"""The FEM job: the reference a calibration's chains fit to, solved once per FEM hash."""

from __future__ import annotations

import json
import time
from typing import Any

from fpm import load_problem
from fpm.fem.reference import FemError, solve_fem
from store import records
from store.status import FemStatus

from .. import memory
from .context import _job


def fem_reference(fem_hash: str) -> dict[str, Any]:
    """Solve and store the FEM reference ``fem_hash`` (no expiry). Returns a summary."""
    redis = _job().connection
    if records.has_fem_reference(redis, fem_hash):
        return {"id": fem_hash, "cached": True}
    meta = records.get_fem_meta(redis, fem_hash)
    cpu = time.process_time()
    records.update_fem_meta(redis, fem_hash, {"status": FemStatus.RUNNING, "started": time.time()})
    try:
        spec = json.loads(meta["spec"])
        mesh_id = (spec.get("reference") or {}).get("mesh_id")
        mesh = records.get_mesh(redis, mesh_id) if mesh_id else None
        if mesh_id and mesh is None:
            raise FemError(f"reference.mesh_id: no uploaded mesh {mesh_id}")
        problem = load_problem(spec, mesh)  # its tags, if material.regions select by them
        memory.check(problem.n_nodes)  # refused before it starts, not killed halfway

        def level(info: dict[str, Any]) -> None:  # the calibrations' progress shows it
            records.update_fem_meta(redis, fem_hash, info)

        result = solve_fem(problem, mesh=mesh, progress=level)
    except FemError as e:
        # The problem cannot be solved (e.g. the solid is not held): a retry would fail the
        # same way, so the reference fails now and the chains waiting on it say why.
        failed = {"status": FemStatus.FAILED, "error": str(e), "finished": time.time()}
        records.update_fem_meta(redis, fem_hash, failed)
        return {"id": fem_hash, "failed": True}
    fields = {
        "status": FemStatus.SUCCEEDED,
        "finished": time.time(),
        "worker": _job().worker_name or "?",  # the calibrations' timelines (finalize)
        "cpu": time.process_time() - cpu,
        "n_nodes": len(result.nodes),
        "load_cases": result.load_cases,  # lists and dicts are stored as JSON
        "model": result.model,
        "element": result.element,
        "solver": {
            "residuals": [float(r) for r in result.residuals],
            "load_steps": list(result.load_steps),
            "newton_iterations": [list(n) for n in result.newton_iterations],
            "estimated_error": result.estimated_error,
            "refinements": result.refinements,
            "loads": result.loads,
            "levels": result.levels,
            "notes": result.notes,
        },
    }
    records.save_fem_reference(redis, fem_hash, *result.to_stored(), fields)
    return {"id": fem_hash, "cached": False, "n_nodes": len(result.nodes)}
