"""The jobs' spans for a calibration's timeline (:mod:`store.timeline`) and its critical path."""

from __future__ import annotations

import time
from typing import Any

from redis import Redis
from rq.job import Job

from store import records, scratch
from store.timeline import critical_path, numbered

FEM_SPAN = "FEM reference"
"""The FEM job's span name (it ran for the calibration unless the reference was stored)."""
BASIS_SPAN = "reduced basis"
"""The reduced-basis job's span name (families+volume calibrations only)."""


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
