"""A text progress bar for a calibration, and a line for other waits, drawn on stderr (no
dependencies)."""

from __future__ import annotations

import sys
from typing import Any, TextIO

from .table import printable

WIDTH = 30


def fraction_done(calibration: dict[str, Any]) -> float:
    """Annealing moves done over moves in all (1 once succeeded). The stages after the
    annealing (damping, finalize) have no known length: the line names them instead."""
    if calibration["status"] == "succeeded":
        return 1.0
    p = calibration["progress"]
    total = p.get("total_iterations") or 0
    return min(p.get("iterations", 0) / total, 1.0) if total else 0.0


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
    """One line: name, bar, percent, status, phase, then the annealing's temperature and best
    cost, or in the damping stage its step and the d values tried."""
    p = calibration["progress"]
    fraction = fraction_done(calibration)
    filled = round(fraction * WIDTH)
    name = printable(calibration.get("name", ""))
    line = f"{name[:28]:<28} [{'#' * filled}{'.' * (WIDTH - filled)}]"
    line += f" {fraction:4.0%} {calibration['status']:<9} {phase_label(p):<9}"
    if p["phase"] == "damping":
        damping = p.get("damping") or {}
        line += f" {DAMPING_STEPS.get(damping.get('step') or '', 'starting')}"
        if damping.get("runs"):
            line += f" d tried={damping['runs']}"
        if damping.get("best_d") is not None:
            line += f" fastest d={damping['best_d']:.3g}"
        return line.rstrip()
    if p.get("temperature") is not None:
        line += f" T={p['temperature']:.2e}"
    if p.get("best_cost") is not None:
        line += f" best={p['best_cost']:.4f}"
    return line.rstrip()


class ProgressBar:
    """Redraws one line on a terminal; on a pipe, prints a line per 10%, change of phase or
    step of the damping stage."""

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
                str((p.get("damping") or {}).get("step")),
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
