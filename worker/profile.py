"""The FPM-vs-FEM displacement profiles of a succeeded calibration, as data (the web view's plot).

The same profiles ``fpmcal calibrate --plot`` draws (:mod:`fpm.io.plot`): per load case the
axis-parallel line through its first loaded node that holds the most nodes
(:func:`fpm.io.plot.profile_line`), with the displacement magnitude of the FEM reference and of an
FPM run at the fitted stiffness, d and depth at those nodes. The FPM run needs the numerical
kernels, which the service never loads (docs/service.md), so a worker computes it: the service
enqueues :func:`calibration_profile` once (:func:`store.graph.request_profile`) and answers from
the stored data (:func:`store.scratch.get_profile`) once it is there.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rq import get_current_job

from fpm.fitting.damping.validation import replayed_run
from fpm.io.plot import profile_line
from store import records, scratch
from store.status import CalibrationStatus

from .problems import problem_of, reference_of


def profile_data(problem: Any, reference: Any, result: dict[str, Any]) -> list[dict[str, Any]]:
    """Per load case: the profile line and the FEM and FPM displacement magnitudes along it.

    Args:
        problem: the calibration's :class:`fpm.Problem`.
        reference: (L, N, 3) FEM displacements, m.
        result: the stored calibration result (k, stiffness, d, depth and the figures).

    Returns:
        One dict per load case: name, axis (the line's, "x"/"y"/"z"), force_axis, nodes (indices
        along the line), position (m, along the axis), fem and fpm (displacement magnitudes,
        m), the fit figures of the result (relative_discrepancy, loaded_discrepancy,
        discrepancy_h, %) and the run's steps and settled flag.
    """
    reference = np.asarray(reference, dtype=float)
    out = []
    for j, case in enumerate(problem.load_cases):
        line, along, direction = profile_line(problem, j)
        run = replayed_run(problem, result, j)
        p, q = run.displacements, reference[j]
        out.append(
            {
                "name": case.name,
                "axis": "xyz"[along],
                "force_axis": "xyz"[direction],
                "nodes": [int(i) for i in line],
                "position": [float(v) for v in problem.nodes[line, along]],
                "fem": [float(v) for v in np.linalg.norm(q[line], axis=1)],
                "fpm": [float(v) for v in np.linalg.norm(p[line], axis=1)],
                "relative_discrepancy": result["relative_discrepancy"][j],
                "loaded_discrepancy": result["loaded_discrepancy"][j],
                "discrepancy_h": result["discrepancy_h"][j],
                "steps": int(run.steps),
                "settled": bool(run.settled),
            }
        )
    return out


def calibration_profile(calibration_id: str) -> dict[str, Any]:
    """RQ job: compute and store the profile data of a succeeded calibration.

    Stores ``{"status": "ready", "h", "load_cases"}``, or ``{"status": "failed", "error"}`` for
    :data:`store.scratch.PROFILE_FAILED_TTL` seconds when it cannot be computed (no result,
    reference gone, a run that raises), so the service answers with the reason instead of
    enqueueing again at every poll.
    """
    job = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    redis = job.connection
    if scratch.has_profile(redis, calibration_id):
        return {"skipped": True}
    record = records.get_calibration(redis, calibration_id)
    reference = reference_of(redis, record.fem_hash) if record else None
    error = None
    if record is None or record.status != CalibrationStatus.SUCCEEDED or not record.result:
        error = "the calibration has no result"
    elif reference is None:
        error = "its FEM reference is no longer stored"
    if error is None:
        assert record is not None and record.result is not None and reference is not None
        try:
            problem = problem_of(redis, record.spec)
            cases = profile_data(problem, reference.displacements, record.result)
        except Exception as e:  # stored and shown: a retry would fail the same way
            error = f"{type(e).__name__}: {e}"
        else:
            data = {"status": "ready", "h": problem.h, "load_cases": cases}
            scratch.save_profile(redis, calibration_id, data)
            return {"load_cases": len(cases)}
    scratch.save_profile(redis, calibration_id, {"status": "failed", "error": error})
    return {"failed": error}
