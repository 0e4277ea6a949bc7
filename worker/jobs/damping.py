"""The damping job: stage 2 of the two-stage method, its runs spread over the free workers."""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from fpm.fitting.calibration import (
    fit_stage,
)
from fpm.fitting.damping.choice import DampingPlan
from fpm.fitting.damping.unsettled import DampingError, Hopeless
from fpm.fitting.damping.validation import validate
from store import records, scratch
from store.status import Phase

from .. import memory
from ..problems import problem_of
from ..spread import CaseSpread, ValidationTask
from ..tasks import save_targets
from .basis import _stored_basis
from .chains import _chains_and_reference
from .context import Canceled, _calibration_job
from .failure import _fail
from .progress import _DampingProgress
from .spans import _Span

DAMPING_HINT = "lower fpm.dt, widen annealing.bounds.d, or raise fpm.max_steps"
"""What to change when no d settles every load case."""


SPREAD_TIMEOUT = 6 * 3600
"""A load-case job's timeout when the damping job has none, s."""


def fit_damping_stage(calibration_id: str) -> dict[str, Any]:
    """Two-stage, stage 2: polish the stiffness, resolve the depth, find the fastest d.

    Its result is written once (a retried job that finds it does nothing; one stopped half-way
    starts again, as it is deterministic and keeps no checkpoint). Progress: the field
    ``keys.DAMPING_PROGRESS`` of the progress hash.
    """
    opened = _calibration_job(calibration_id)
    if opened is None:
        return {"skipped": True}
    job, redis, record = opened
    if scratch.has_damping_result(redis, calibration_id):
        return {"skipped": True}
    if not records.update_calibration(redis, calibration_id, {"phase": Phase.DAMPING}):
        return {"skipped": True}  # canceled (or failed) meanwhile
    found = _chains_and_reference(redis, record)
    if found is None:
        return {"failed": True}
    chains, reference = found
    problem = problem_of(redis, record.spec)
    memory.check(problem.n_nodes)
    reporter = _DampingProgress(job, calibration_id)
    span = _Span(job, calibration_id, "damping", [f"chain {c}" for c in range(record.chains)])
    spreads: list[CaseSpread] = []
    timeout = job.timeout if isinstance(job.timeout, int) else SPREAD_TIMEOUT

    def spread(plan: DampingPlan, targets: np.ndarray | None) -> CaseSpread | None:
        """The d search's runs over the free workers (not a field's: its stiffness is not
        rebuilt from theta), with the static equilibria they settle towards."""
        if plan.field:
            return None
        if targets is not None:
            save_targets(redis, calibration_id, targets)
        spreads.append(
            CaseSpread(
                redis, calibration_id, plan, span.worker, timeout,
                lambda: reporter.report(reporter.info),  # raises Canceled
            )
        )  # fmt: skip
        return spreads[-1]

    validator = ValidationTask(
        redis, calibration_id, span.worker, timeout, partial(validate, problem, reference)
    )
    try:
        basis = _stored_basis(redis, calibration_id)
        stage = fit_stage(
            problem, reference, chains, progress=reporter, spread=spread, basis=basis,
            validator=validator,
        )  # fmt: skip
        reporter.flush()
    except Canceled:
        return {"canceled": True}
    except (RuntimeError, ValueError) as e:
        # DampingError (no d in the bounds settles every load case) or a static solve that
        # failed: a retry would fail the same way, so the calibration fails now.
        # (a case that cannot settle says what helps it: another cap or dt would not)
        plain = isinstance(e, DampingError) and not isinstance(e, Hopeless)
        hint = f": {DAMPING_HINT}" if plain else ""
        _fail(redis, calibration_id, f"damping stage failed: {e}{hint}")
        return {"failed": True}
    scratch.save_damping_result(redis, calibration_id, stage.to_dict())
    here = validator.cpu + (spreads[0].cpu if spreads else 0.0)  # tasks with spans of their own
    first = spreads[0] if spreads else None
    span.add_around(
        first.rounds if first else [], here, reporter.marks, first.first_cpu if first else None
    )
    return {"d": stage.d, "depth": stage.depth, "runs": stage.damping_runs}
