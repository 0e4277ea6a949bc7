"""The export job: a stored parameter set in one format, made once and cached."""

from __future__ import annotations

from typing import Any

from fpm.io.export import ExportError, export
from store import records, scratch
from store.hashing import export_hash

from ..problems import problem_of, reference_of
from .context import _job


def export_parameter_set(parameter_set_id: str, fmt: str) -> dict[str, Any]:
    """Make and cache the export of a stored parameter set in ``fmt`` (``json``, ``vtu`` or
    ``sofa``: :func:`fpm.io.export.export`), which the service hands out
    (:func:`store.graph.request_export`).

    The lattice is rebuilt from the spec in the calibration record the set's provenance names;
    ``vtu`` takes the FEM displacements from the stored reference and runs the FPM at the
    parameters. A failure is stored, not raised, for the cool-down
    (:data:`store.scratch.EXPORT_FAILED_TTL`), so that polling does not re-run it at once:
    ``invalid`` when the parameters do not fit the lattice (:class:`fpm.io.export.ExportError`),
    else an error a later run may not repeat. Returns a summary.
    """
    redis = _job().connection
    digest = export_hash(parameter_set_id, fmt)
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
        fem = None
        if fmt == "vtu":
            stored = reference_of(redis, str(provenance.get("fem_hash", "")))
            fem = None if stored is None else stored.displacements
        body = export(problem_of(redis, record.spec), ps, fmt, fem=fem)
    except ExportError as e:
        error, invalid = str(e), True
    except Exception as e:  # stored and shown; tried again after the cool-down
        error = f"{type(e).__name__}: {e}"
    else:
        scratch.save_export(redis, digest, body)
        return {"bytes": len(body)}
    scratch.save_export_failure(redis, digest, error, invalid)
    return {"failed": error}
