"""The finalize job: the last dynamic run, the figures, the stored parameter set and result."""

from __future__ import annotations

import time
from typing import Any

from fpm.fitting.calibration import (
    DampingStage,
    check_reference,
    finalize,
)
from store import keys, records, scratch
from store.status import CalibrationStatus, Phase

from .. import memory
from ..problems import problem_of
from .chains import _chains_and_reference
from .context import _calibration_job
from .failure import _fail
from .spans import _Span, _timeline


def finalize_calibration(calibration_id: str) -> dict[str, Any]:
    """The last dynamic run and the figures; store the parameter set and the result, with the
    timeline of the calibration's jobs and its critical path (:mod:`store.timeline`)."""
    opened = _calibration_job(calibration_id)
    if opened is None:
        return {"skipped": True}
    job, redis, record = opened
    span = _Span(job, calibration_id, "finalize", [])
    records.update_calibration(redis, calibration_id, {"phase": Phase.FINALIZE})
    found = _chains_and_reference(redis, record)
    if found is None:
        return {"failed": True}
    chains, reference = found
    damping = None
    if record.spec["annealing"]["method"] == "two-stage":
        saved = scratch.get_damping_result(redis, calibration_id)
        if saved is None:
            _fail(redis, calibration_id, "the damping stage did not finish")
            return {"failed": True}
        damping = DampingStage.from_dict(saved)
    problem = problem_of(redis, record.spec)
    memory.check(problem.n_nodes)
    warnings = check_reference(problem, reference)
    result = finalize(problem, reference, chains, damping, warnings=warnings).to_dict()
    result.update(_timeline(redis, record, span))
    parameter_set = _parameter_set(record, result, problem.n_nodes)
    tasks = scratch.case_tasks(redis, calibration_id)

    def store_once(pipe: Any) -> None:
        records.write_parameter_set(pipe, parameter_set)
        scratch.delete_stage_data(pipe, calibration_id, record.chains, tasks)

    records.update_calibration(
        redis,
        calibration_id,
        {
            "status": CalibrationStatus.SUCCEEDED,
            "phase": Phase.DONE,
            "finished": time.time(),
            "result": result,
            "parameter_set_id": parameter_set.id,
        },
        extra=store_once,
    )
    return {"parameter_set_id": parameter_set.id}


def _parameter_set(
    record: records.CalibrationRecord, result: dict[str, Any], n_nodes: int
) -> records.ParameterSetRecord:
    """The stored (k, d, depth) with the material, a geometry summary and the provenance.

    Its id comes from the spec hash, so one spec stores at most one parameter set.
    """
    spec = record.spec
    geometry = spec["geometry"]
    return records.ParameterSetRecord(
        id=keys.parameter_set_id(record.spec_hash),
        created=time.time(),
        name=record.name,
        k=result["k"],
        stiffness=result["stiffness"],
        stiffness_mode=spec["fpm"]["stiffness"],
        volume_stiffness=result.get("volume_stiffness"),
        field=result.get("field"),
        d=result["d"],
        d_min=result["d_min"],
        depth=result["depth"],
        dt=result.get("dt") or spec["fpm"]["dt"],  # 'auto' resolved by the fit
        stiffness_scale=spec["fpm"]["stiffness_scale"],
        material=spec["material"],
        geometry=records.GeometrySummary(
            type=geometry["type"],
            connectivity=geometry.get("connectivity"),
            size=geometry.get("size"),
            nodes=n_nodes,
            h=result["h"],
        ),
        relative_discrepancy=result["relative_discrepancy"],
        loaded_discrepancy=result["loaded_discrepancy"],
        discrepancy_h=result["discrepancy_h"],
        validation_cases=result.get("validation_cases", []),
        validation_relative_discrepancy=result.get("validation_relative_discrepancy", []),
        validation_discrepancy_h=result.get("validation_discrepancy_h", []),
        compliance_ratio=result.get("compliance_ratio", []),
        validation_compliance_ratio=result.get("validation_compliance_ratio", []),
        verdict=result.get("verdict"),
        node_mass=result["node_mass"],
        warnings=result["warnings"],
        cost=result["cost"],
        provenance=records.Provenance(
            calibration_id=record.id,
            spec_hash=record.spec_hash,
            fem_hash=record.fem_hash,
            method=result["method"],
            seed=spec["annealing"]["seed"],
            chains=record.chains,
            evaluations=result["evaluations"],
        ),
    )
