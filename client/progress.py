"""A text progress bar for a calibration, and a line for other waits, drawn on stderr (no
dependencies)."""

from __future__ import annotations

import sys
from typing import Any, TextIO

from .table import printable

WIDTH = 30


def fraction_done(calibration: dict[str, Any]) -> float:
    """How far the calibration is, 0-1, counted in its stages (``progress.stages``), not in
    time: each stage an equal share, filled within the annealing by its moves done and within
    the damping stage by its steps begun (polish, depth, field, d search); 1 once succeeded.
    The FEM reference and the d search have no known length, so the bar waits at their
    stage's start rather than claiming a share it cannot measure. A server that sends no
    ``stages`` gets the annealing's own fraction."""
    if calibration["status"] == "succeeded":
        return 1.0
    p = calibration["progress"]
    stages = p.get("stages") or []
    if p["phase"] not in stages:
        return 0.0 if stages else _within(p)
    return (stages.index(p["phase"]) + _within(p)) / len(stages)


def _within(progress: dict[str, Any]) -> float:
    """The fraction of the current stage done, where it is known (else 0)."""
    if progress["phase"] == "annealing":
        total = progress.get("total_iterations") or 0
        return min(progress.get("iterations", 0) / total, 1.0) if total else 0.0
    if progress["phase"] == "damping":
        step = (progress.get("damping") or {}).get("step")
        return list(DAMPING_STEPS).index(step) / len(DAMPING_STEPS) if step in DAMPING_STEPS else 0
    return 0.0


PHASE_LABELS = {"annealing": {"two-stage": "stiffness", "paper": "annealing"}}
"""Short phase names for the bar: the two-stage method's annealing is its stiffness search."""


DAMPING_STEPS = {
    "polish": "polish",
    "depth": "depth",
    "field": "stiffness field",
    "damping": "d search",
}
"""The damping stage's steps as the bar shows them."""


def phase_label(progress: dict[str, Any]) -> str:
    """The phase, as the bar shows it ('stiffness' for the two-stage method's annealing)."""
    phase = progress["phase"]
    return PHASE_LABELS.get(phase, {}).get(progress.get("method", ""), phase)


def render(calibration: dict[str, Any]) -> str:
    """One line: name, bar, percent (:func:`fraction_done`), status, stage k of n, phase, then
    the annealing's temperature and best cost, in the damping stage its step and the d values
    tried, or in the FEM stage the reference's refinement level, FEM nodes and last change."""
    p = calibration["progress"]
    fraction = fraction_done(calibration)
    filled = round(fraction * WIDTH)
    name = printable(calibration.get("name", ""))
    line = f"{name[:28]:<28} [{'#' * filled}{'.' * (WIDTH - filled)}]"
    line += f" {fraction:4.0%} {calibration['status']:<9}"
    stages = p.get("stages") or []
    if p["phase"] in stages:  # the service's number (a server before it: the same, counted)
        line += f" stage {p.get('stage_number') or stages.index(p['phase']) + 1}/{len(stages)}"
    line += f" {phase_label(p):<9}"
    if p["phase"] == "damping":
        damping = p.get("damping") or {}
        line += f" {DAMPING_STEPS.get(damping.get('step') or '', 'starting')}"
        if damping.get("runs"):
            line += f" d tried={damping['runs']}"
        if damping.get("best_d") is not None:
            line += f" fastest d={damping['best_d']:.3g}"
        return line.rstrip()
    fem = p.get("fem") or {}
    if p["phase"] == "fem" and fem.get("level") is not None:
        line += f" level {fem['level']}: {fem['fem_nodes']:,} nodes"
        if fem.get("last_change") is not None:
            line += f", last change {fem['last_change']:.2g}%"
        return line.rstrip()
    if p.get("temperature") is not None:
        line += f" T={p['temperature']:.2e}"
    if p.get("best_cost") is not None:
        line += f" best={p['best_cost']:.4f}"
    return line.rstrip()


class ProgressBar:
    """Redraws one line on a terminal; on a pipe, prints a line per 10%, change of phase, step
    of the damping stage or level of the FEM reference."""

    def __init__(self, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.last = ""
        self.last_key: tuple[str, str, int, str] | None = None

    def update(self, calibration: dict[str, Any]) -> None:
        line = render(calibration)
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self.last)))
        else:
            p = calibration["progress"]
            key = (
                calibration["status"],
                p["phase"],
                int(fraction_done(calibration) * 10),
                f"{(p.get('damping') or {}).get('step')}/{(p.get('fem') or {}).get('level')}",
            )
            if key == self.last_key:
                return
            self.last_key = key
            self.stream.write(line + "\n")
        self.last = line
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self.last:
            self.stream.write("\n")
            self.stream.flush()


class WaitLine:
    """A wait of unknown length (an export the service makes) on stderr: on a terminal one line
    redrawn with the seconds waited; on a pipe the line once, then how it ended."""

    def __init__(self, what: str, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.what = printable(what)
        self.shown = False

    def update(self, seconds: float) -> None:
        if self.tty:
            self.stream.write(f"\r{self.what} ... {seconds:.0f} s")
        elif not self.shown:
            self.stream.write(f"{self.what} ...\n")
        self.shown = True
        self.stream.flush()

    def close(self, seconds: float, done: bool = True) -> None:
        end = f"ready after {seconds:.0f} s" if done else f"still waiting after {seconds:.0f} s"
        self.stream.write(f"\r{self.what} ... {end}\n" if self.tty else f"{self.what}: {end}\n")
        self.stream.flush()
