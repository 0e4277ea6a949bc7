"""RQ job functions: FEM reference, stage 1's reduced basis (families+volume), one annealing
chain, the damping stage (two-stage method), finalize, and the export of a parameter set
(enqueued by dotted path).

Every job takes ids only and reads what it needs from our keys; every job may run twice
(a retry after its worker died) and writes its results once, under deterministic keys:
a stored reduced basis is not built again, a finished chain is not re-run (nor one that an
earlier calibration of the same stiffness fit ran: its result is kept by the fit's identity,
:func:`store.hashing.stiffness_hash`, so a calibration run again after its damping stage
failed, or with other damping settings, resumes from the stored FEM reference and chains), a
stopped chain resumes from its checkpoint, a finished damping stage is not re-run (an
interrupted one starts again: it is deterministic), and the parameter set is written with SET
NX.

Progress goes to the calibration's progress hash (:func:`store.keys.calibration_progress`):
one field per chain, and the field :data:`store.keys.DAMPING_PROGRESS` for the damping stage.
Each progress write also reads the calibration's status, and a job whose calibration has been
canceled (or failed elsewhere) stops there.
"""

from __future__ import annotations

import json
import time
from functools import partial
from typing import Any

import numpy as np
from redis import Redis
from rq import get_current_job
from rq.job import Job

from fpm import load_problem
from fpm.fem.reference import FemError, FemResult, solve_fem
from fpm.fitting.annealing import AnnealingError, Checkpoint
from fpm.fitting.calibration import (
    ChainResult,
    DampingStage,
    check_reference,
    finalize,
    fit_stage,
    run_chain,
)
from fpm.fitting.damping.search import DampingPlan
from fpm.fitting.damping.unsettled import DampingError, Hopeless
from fpm.fitting.damping.validation import validate
from fpm.fitting.reduced import ReducedBasis, first_basis
from fpm.io.export import ExportError, export
from store import keys, records, scratch
from store.hashing import export_hash, stiffness_hash
from store.status import CalibrationStatus, FemStatus, Phase
from store.timeline import critical_path, numbered

from . import memory
from .problems import problem_of, reference_of
from .spread import CaseSpread, ValidationTask, save_targets

PROGRESS_INTERVAL = 0.5
"""Seconds between progress writes of a job (each also checks for a cancel)."""

DAMPING_HINT = "lower fpm.dt, widen annealing.bounds.d, or raise fpm.max_steps"
"""What to change when no d settles every load case."""


class Canceled(Exception):
    """The calibration was canceled (or failed elsewhere) while this job was running."""


def _job() -> Job:
    job = get_current_job()
    if job is None:
        raise RuntimeError("not running inside an RQ job")
    return job


def _calibration_job(calibration_id: str) -> tuple[Job, Redis, records.CalibrationRecord] | None:
    """This job, its connection and calibration ``calibration_id``'s record; None when the
    calibration is gone or has ended (the job has nothing to do)."""
    job = _job()
    redis = job.connection
    record = records.get_calibration(redis, calibration_id)
    if record is None or record.status.terminal:
        return None
    return job, redis, record


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


class _Reporter:
    """Writes a job's progress to one field of the calibration's progress hash and to the job
    meta.

    At most every PROGRESS_INTERVAL seconds (or at once when asked); each write also reads the
    calibration's status and raises :class:`Canceled` once it is terminal, so a canceled job
    stops even on a worker that cannot kill its work horse (SimpleWorker).
    """

    def __init__(self, job: Job, calibration_id: str, field: str):
        self.job = job
        self.calibration_id = calibration_id
        self.field = field
        self.last = 0.0
        self.info: dict[str, Any] = {}

    def report(self, info: dict[str, Any], *, now: bool = False) -> None:
        self.info = info
        if now or time.monotonic() - self.last >= PROGRESS_INTERVAL:
            self.flush()

    def flush(self) -> None:
        """Write the latest report now."""
        self.last = time.monotonic()
        going_on = scratch.report_progress(
            self.job.connection, self.calibration_id, self.field, self.info
        )
        self.job.meta["progress"] = self.info
        self.job.save_meta()
        if not going_on:
            raise Canceled(self.calibration_id)


class _ChainProgress(_Reporter):
    """A chain's progress: {move, moves, temperature, best_cost}."""

    def __init__(self, job: Job, calibration_id: str, chain: int):
        super().__init__(job, calibration_id, str(chain))

    def __call__(self, info: dict[str, Any]) -> None:
        keep = ("move", "moves", "temperature", "best_cost")
        self.report({k: info[k] for k in keep if k in info})


class _DampingProgress(_Reporter):
    """The damping stage's progress: {step, runs, d, total_steps, best_d, best_total_steps}.

    ``step`` is "polish", "depth", "field" or "damping" (fpm.fitting.damping.stage.fit_stage's
    phases),
    written at once when it changes; ``runs`` counts the d values tried, ``d`` and
    ``total_steps`` are the last one's (total_steps None: some load case did not settle) and
    ``best_*`` the fastest so far. ``marks``: (step, Unix s, process CPU s) where each step
    began (the damping span's phases, :meth:`_Span.add_around`).
    """

    def __init__(self, job: Job, calibration_id: str):
        super().__init__(job, calibration_id, keys.DAMPING_PROGRESS)
        self.marks: list[tuple[str, float, float]] = []
        self.state: dict[str, Any] = {
            "step": None,
            "runs": 0,
            "d": None,
            "total_steps": None,
            "best_d": None,
            "best_total_steps": None,
        }

    def __call__(self, info: dict[str, Any]) -> None:
        step = info.get("phase")
        changed = step != self.state["step"]
        self.state["step"] = step
        if changed:
            self.marks.append((str(step), time.time(), time.process_time()))
        if "d" in info:
            total = info.get("total_steps")
            self.state.update(runs=self.state["runs"] + 1, d=info["d"], total_steps=total)
            best = self.state["best_total_steps"]
            if total is not None and (best is None or total < best):
                self.state.update(best_d=info["d"], best_total_steps=total)
        self.report(dict(self.state), now=changed)


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


FEM_SPAN = "FEM reference"
"""The FEM job's span name (it ran for the calibration unless the reference was stored)."""
BASIS_SPAN = "reduced basis"
"""The reduced-basis job's span name (families+volume calibrations only)."""
SPREAD_TIMEOUT = 6 * 3600
"""A load-case job's timeout when the damping job has none, s."""


class _Span:
    """A job's span for the calibration's timeline (:mod:`store.timeline`): started when made,
    added by :meth:`add` (or :meth:`add_around`)."""

    def __init__(self, job: Job, calibration_id: str, name: str, after: list[str]):
        self.redis, self.calibration_id, self.name = job.connection, calibration_id, name
        self.after = after
        self.worker = job.worker_name or "?"
        self.start, self.cpu = time.time(), time.process_time()

    def as_dict(self, start: float, end: float, cpu: float, after: list[str]) -> dict[str, Any]:
        return {"name": self.name, "worker": self.worker, "start": start, "end": end,
                "cpu": cpu, "after": after}  # fmt: skip

    def add(self, less: float = 0.0) -> None:
        """The span from its start to now; its CPU seconds are the process's less ``less``
        (those of tasks run on its threads that have spans of their own)."""
        cpu = max(time.process_time() - self.cpu - less, 0.0)
        span = self.as_dict(self.start, time.time(), cpu, self.after)
        scratch.add_span(self.redis, self.calibration_id, span)

    def add_around(
        self,
        rounds: list[tuple[float, float, list[str]]],
        tasks_cpu: float,
        marks: list[tuple[str, float, float]] | None = None,
        first_cpu: float | None = None,
    ) -> None:
        """The damping job, in segments around its hand-outs of tasks (``rounds``:
        :attr:`worker.spread.CaseSpread.rounds`): "<name>" up to the first, "<name> (k)"
        between hand-outs k - 1 and k, waiting for the tasks of the one before, "<name>
        (gather)" from the last on; with no hand-out one span. The job's CPU seconds go on the
        first, less ``tasks_cpu``, those of the tasks it ran on its threads (their own spans
        count them). ``marks`` ((step, Unix s, CPU s) where each phase of the stage began):
        the first segment's ``phases``, [{phase, seconds, cpu}] up to its end, which say what
        the job did alone before its first hand-out (``first_cpu``: the process's CPU seconds
        then) and on how many cores."""
        if not rounds:
            self.add(tasks_cpu)
            return
        phases = []
        handed = time.process_time() if first_cpu is None else first_cpu
        marks = [("load", self.start, self.cpu), *(marks or [])]  # the problem, the chains
        ends = [(t, c) for _, t, c in marks[1:]] + [(rounds[0][0], handed)]
        for (step, t0, c0), (t1, c1) in zip(marks, ends, strict=True):
            if t0 < rounds[0][0]:
                end = min(t1, rounds[0][0])
                phases.append({"phase": step, "seconds": end - t0, "cpu": max(c1 - c0, 0.0)})
        edges = [self.start] + [t for r in rounds for t in r[:2]] + [time.time()]
        for k in range(len(rounds) + 1):
            start, end = edges[2 * k], edges[2 * k + 1]
            after = self.after if k == 0 else rounds[k - 1][2]
            cpu = max(time.process_time() - self.cpu - tasks_cpu, 0.0) if k == 0 else 0.0
            span = self.as_dict(start, end, cpu, after)
            if k == 0 and phases:
                span["phases"] = phases
            if k:
                span["name"] = f"{self.name} ({'gather' if k == len(rounds) else k})"
            scratch.add_span(self.redis, self.calibration_id, span)


def _timeline(redis: Redis, record: records.CalibrationRecord, own: _Span) -> dict[str, Any]:
    """The result's ``jobs`` (the FEM job's span when it ran for this calibration, every
    span in start order, finalize's last) and ``critical_path`` / ``critical_path_seconds``
    (:func:`store.timeline.critical_path`)."""
    spans = numbered(scratch.get_spans(redis, record.id))
    meta = records.get_fem_meta(redis, record.fem_hash)
    if not record.fem_cached and meta.get("started") and meta.get("finished"):
        fem = {"name": FEM_SPAN, "worker": meta.get("worker") or "?",
               "start": float(meta["started"]), "end": float(meta["finished"]),
               "cpu": float(meta.get("cpu") or 0.0), "after": []}  # fmt: skip
        spans.append(fem)
    waited = {a for s in spans for a in s["after"]}
    last = [s["name"] for s in spans if s["name"] not in waited]  # finalize waits for them
    spans.append(own.as_dict(own.start, time.time(), time.process_time() - own.cpu, last))
    spans.sort(key=lambda s: s["start"])
    seconds, path = critical_path(spans)
    return {"jobs": spans, "critical_path": path, "critical_path_seconds": seconds}


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


def _fail(redis: Redis, calibration_id: str, error: str) -> None:
    records.update_calibration(
        redis,
        calibration_id,
        {"status": CalibrationStatus.FAILED, "error": error, "finished": time.time()},
    )


def on_failure(job: Job, connection: Redis, exc_type: type, value: BaseException, tb: Any) -> None:
    """RQ failure callback of every job: record the failure once no retry is left.

    A calibration job (chain, damping, finalize) fails its calibration, which stops the
    others;
    the FEM job marks its reference failed, and the chains waiting on it then fail their
    calibrations (they run anyway: their dependency allows failure).
    """
    if job.retries_left:
        return
    error = f"{exc_type.__name__}: {value}" if str(value) else exc_type.__name__
    if job.func_name == keys.FEM_JOB:
        failed = {"status": FemStatus.FAILED, "error": error, "finished": time.time()}
        records.update_fem_meta(connection, job.args[0], failed)
    else:
        _fail(connection, job.args[0], f"{job.description}: {error}")
