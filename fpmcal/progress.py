"""Progress on stderr while ``fpmcal`` works in-process: the calibration's bar, the refined FEM
reference's levels."""

from __future__ import annotations

import sys
from typing import Any


class _Bar:
    """A one-line progress bar on stderr for in-process calibration (chains share the bar; its
    best cost is the best so far over all of them, so a chain starting later never raises it)."""

    def __init__(self, chains: int, moves: int):
        self.done = [0] * chains
        self.best = float("inf")
        self.total = chains * moves
        self.tty = sys.stderr.isatty()
        self.last_tenth = -1
        self.phase: Any = None

    def __call__(self, info: dict[str, Any]) -> None:
        if info.get("phase") != "annealing":
            if info.get("phase") != self.phase:  # once per phase, not per report
                print(f"  {info.get('phase')} ...", file=sys.stderr, flush=True)
            self.phase = info.get("phase")
            if info.get("phase") == "damping" and "d" in info:  # a line per d tried
                total = info.get("total_steps")
                steps = "not settled (or slower)" if total is None else f"{total:,} steps"
                print(f"    d = {info['d']:.4g} N s/m: {steps}", file=sys.stderr, flush=True)
            return
        if "best_cost" not in info:  # still drawing the chain's starting point
            return
        self.done[info["chain"]] = info["move"]
        self.best = min(self.best, info["best_cost"])
        frac = sum(self.done) / self.total
        if not self.tty and int(frac * 10) == self.last_tenth:
            return
        self.last_tenth = int(frac * 10)
        bar = "#" * round(30 * frac)
        line = f"  annealing [{bar:<30}] {frac:4.0%}  T={info['temperature']:.2e}"
        line += f"  best cost {self.best:.4f}"
        print(("\r" if self.tty else "") + line, end="" if self.tty else "\n", file=sys.stderr)
        if self.tty and frac >= 1:
            print(file=sys.stderr)


def _fem_levels(info: dict[str, Any]) -> None:
    """A line on stderr per level of a refined FEM reference as it starts (it can take
    minutes on an organ)."""
    change = info.get("last_change")
    after = f" (the last two levels differ by {change:.2g}%)" if change is not None else ""
    print(
        f"FEM reference: refinement level {info['level']}, {info['fem_nodes']:,} FEM nodes{after}",
        file=sys.stderr,
    )
