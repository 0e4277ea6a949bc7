"""The chain jobs: one annealing chain each, resumed from its checkpoint or reused from an
earlier calibration of the same fit; the finished chains read back for the jobs after them."""

from __future__ import annotations

import time
from typing import Any

from redis import Redis

from fpm.fem.reference import FemResult
from fpm.fitting.annealing import AnnealingError, Checkpoint
from fpm.fitting.calibration import (
    ChainResult,
    check_reference,
    run_chain,
)
from store import records, scratch
from store.hashing import stiffness_hash
from store.status import CalibrationStatus, Phase

from .. import memory
from ..problems import problem_of, reference_of
from .basis import _stored_basis
from .context import Canceled, _calibration_job
from .failure import _fail
from .progress import _ChainProgress
from .spans import BASIS_SPAN, FEM_SPAN, _Span


def anneal_chain(calibration_id: str, chain: int) -> dict[str, Any]:
    """Run one annealing chain of a calibration and store its ChainResult."""
    opened = _calibration_job(calibration_id)
    if opened is None:
        return {"skipped": True}
    job, redis, record = opened
    if scratch.has_chain_result(redis, calibration_id, chain):
        return {"skipped": True}
    fem = reference_of(redis, record.fem_hash)
    if fem is None:
        error = records.get_fem_meta(redis, record.fem_hash).get("error") or "not computed"
        _fail(redis, calibration_id, f"FEM reference failed: {error}")
        return {"failed": True}
    records.update_calibration(
        redis,
        calibration_id,
        {
            "status": CalibrationStatus.RUNNING,
            "phase": Phase.ANNEALING,
            "started": record.started or time.time(),
        },
    )
    fitted = stiffness_hash(record.spec)
    kept = scratch.get_fitted_chain(redis, fitted, chain)
    if kept is not None:  # an earlier calibration of the same fit ran it (its damping failed)
        scratch.save_chain_result(redis, calibration_id, chain, kept, 0)
        moves = len(kept["history"])  # a finished chain's report: every move made
        done = {"move": moves, "moves": moves, "best_cost": kept["cost"]}
        _ChainProgress(job, calibration_id, chain).report(done, now=True)
        return {"reused": True, "x": kept["x"], "cost": kept["cost"]}
    problem = problem_of(redis, record.spec)
    memory.check(problem.n_nodes)
    try:
        check_reference(problem, fem)
    except ValueError as e:  # units or a load far too large: no annealing can fix it
        _fail(redis, calibration_id, f"reference check failed: {e}")
        return {"failed": True}
    saved = scratch.get_checkpoint(redis, calibration_id, chain)
    reporter = _ChainProgress(job, calibration_id, chain)
    span = _Span(job, calibration_id, f"chain {chain}", [FEM_SPAN, BASIS_SPAN])
    try:
        result = run_chain(
            problem,
            fem,
            chain,
            progress=reporter,
            checkpoint=lambda state: scratch.save_checkpoint(
                redis, calibration_id, chain, state.to_dict()
            ),
            resume=Checkpoint.from_dict(saved) if saved else None,
            basis=_stored_basis(redis, calibration_id),
        )
    except Canceled:
        return {"canceled": True}
    except AnnealingError as e:
        # The spec cannot be fitted (e.g. every candidate diverges): a retry would fail the
        # same way, so the calibration fails now, with the annealer's reason.
        _fail(redis, calibration_id, f"annealing chain {chain} failed: {e}")
        scratch.drop_checkpoint(redis, calibration_id, chain)
        return {"failed": True}
    reporter.flush()
    scratch.save_chain_result(redis, calibration_id, chain, result.to_dict(), result.evaluations)
    scratch.save_fitted_chain(redis, fitted, chain, result.to_dict())  # before the damping stage
    span.add()
    return {"x": result.x, "cost": result.cost, "evaluations": result.evaluations}


def _chains_and_reference(
    redis: Redis, record: records.CalibrationRecord
) -> tuple[list[ChainResult], FemResult] | None:
    """The finished chains' results and the FEM reference, or None (calibration failed)."""
    raws = scratch.get_chain_results(redis, record.id, record.chains)
    missing = [c for c, raw in enumerate(raws) if raw is None]
    if missing:
        _fail(redis, record.id, f"chain(s) {missing} did not finish")
        return None
    reference = reference_of(redis, record.fem_hash)
    if reference is None:
        _fail(redis, record.id, "the FEM reference is gone")
        return None
    chains = [ChainResult.from_dict(raw) for raw in raws]
    return chains, reference
