"""Stage 1's first reduced basis (families+volume): built by its own job beside the FEM job,
read back by every chain and the damping job."""

from __future__ import annotations

from typing import Any

from redis import Redis

from fpm.fitting.annealing import AnnealingError
from fpm.fitting.reduced import ReducedBasis, first_basis
from store import scratch

from .. import memory
from ..problems import problem_of
from .context import _calibration_job
from .spans import BASIS_SPAN, _Span


def reduced_basis(calibration_id: str) -> dict[str, Any]:
    """Build and store stage 1's first reduced basis of a families+volume calibration
    (:func:`fpm.fitting.reduced.first_basis`: from the spec alone, beside the FEM job), which
    every chain and the damping job read instead of building it. Returns a summary."""
    opened = _calibration_job(calibration_id)
    if opened is None:
        return {"skipped": True}
    job, redis, record = opened
    if scratch.has_reduced_basis(redis, calibration_id):
        return {"skipped": True}
    problem = problem_of(redis, record.spec)
    memory.check(problem.n_nodes)
    span = _Span(job, calibration_id, BASIS_SPAN, [])
    try:
        basis = first_basis(problem)
    except AnnealingError as e:  # the chains meet it too, and fail the calibration with it
        return {"failed": str(e)}
    scratch.save_reduced_basis(redis, calibration_id, *basis.to_stored())
    span.add()
    return {"solves": basis.solves, "columns": [c.basis.shape[1] for c in basis.cases]}


def _stored_basis(redis: Redis, calibration_id: str) -> ReducedBasis | None:
    """The calibration's first reduced basis as its job stored it, or None (not built: the
    chain or damping stage that needs it builds it, to the same bits)."""
    stored = scratch.get_reduced_basis(redis, calibration_id)
    return None if stored is None else ReducedBasis.from_stored(*stored)
