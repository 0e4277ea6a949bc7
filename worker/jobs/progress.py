"""A job's progress in the calibration's progress hash: the chains' fields and the damping
stage's; each write also checks for a cancel."""

from __future__ import annotations

import time
from typing import Any

from rq.job import Job

from store import keys, scratch

from .context import Canceled

PROGRESS_INTERVAL = 0.5
"""Seconds between progress writes of a job (each also checks for a cancel)."""


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
