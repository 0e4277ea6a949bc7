"""A text progress bar for a calibration, drawn on stderr (no dependencies)."""

from __future__ import annotations

import sys
from typing import Any, TextIO

WIDTH = 30


def fraction_done(calibration: dict[str, Any]) -> float:
    """Annealing moves done over moves in all (1 once succeeded)."""
    if calibration["status"] == "succeeded":
        return 1.0
    p = calibration["progress"]
    total = p.get("total_iterations") or 0
    return min(p.get("iterations", 0) / total, 1.0) if total else 0.0


def render(calibration: dict[str, Any]) -> str:
    """One line: name, bar, percent, status, phase, temperature and best cost."""
    p = calibration["progress"]
    fraction = fraction_done(calibration)
    filled = round(fraction * WIDTH)
    line = f"{calibration.get('name', '')[:28]:<28} [{'#' * filled}{'.' * (WIDTH - filled)}]"
    line += f" {fraction:4.0%} {calibration['status']:<9} {p['phase']:<9}"
    if p.get("temperature") is not None:
        line += f" T={p['temperature']:.2e}"
    if p.get("best_cost") is not None:
        line += f" best={p['best_cost']:.4f}"
    return line


class ProgressBar:
    """Redraws one line on a terminal; on a pipe, prints a line per 10% or change of phase."""

    def __init__(self, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.last = ""
        self.last_key: tuple[str, str, int] | None = None

    def update(self, calibration: dict[str, Any]) -> None:
        line = render(calibration)
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self.last)))
        else:
            key = (
                calibration["status"],
                calibration["progress"]["phase"],
                int(fraction_done(calibration) * 10),
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
