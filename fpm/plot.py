"""Figures of a calibration: deformation profiles (like paper Fig. 5 and 6) and cost history."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .calibration import CalibrationResult
from .problem import Problem
from .simulation import simulate


def profile_line(problem: Problem, load_case: int = 0) -> tuple[np.ndarray, int, int]:
    """Nodes on the line along x through the first loaded node, sorted by x.

    Returns (node indices (P,), the axis the profile runs along, the force's main axis).
    """
    case = problem.load_cases[load_case]
    first = case.nodes[0]
    direction = int(np.argmax(np.abs(case.forces.sum(axis=0))))
    along = 0 if direction != 0 else 1
    others = [a for a in range(3) if a != along]
    x = problem.nodes
    on = np.all(np.abs(x[:, others] - x[first, others]) <= 1e-6 * problem.h, axis=1)
    line = np.flatnonzero(on)
    return line[np.argsort(x[line, along])], along, direction


def plot_calibration(
    problem: Problem, reference: np.ndarray, result: CalibrationResult, out: str | Path
) -> None:
    """Save a PNG: per load case the FPM and FEM displacement profiles, and the cost history.

    Args:
        reference: (L, N, 3) FEM displacements, m.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = len(problem.load_cases)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for j in range(cases):
        line, along, direction = profile_line(problem, j)
        s = problem.nodes[line, along] * 1e3
        fem_u = reference[j][line, direction] * 1e3
        run = simulate(problem, k=result.k, d=result.d, depth=result.depth, load_case=j)
        colour = f"C{j}"
        ax.plot(s, fem_u, "-", color=colour, label=f"FEM {problem.load_cases[j].name}")
        ax.plot(s, run.displacements[line, direction] * 1e3, "o--", color=colour, ms=4,
                label=f"FPM ({result.discrepancy[j]:.2f}% of h)")  # fmt: skip
    ax.set_xlabel(f"{'xyz'[along]} along the loaded face, mm")
    ax.set_ylabel(f"displacement {'xyz'[direction]}, mm")
    ax.set_title(f"k = {result.k:.4g} N/m, d = {result.d:.4g} N s/m, depth {result.depth}")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    moves = np.arange(1, len(result.history) + 1)
    ax.semilogy(moves, result.history, label="current state")
    ax.semilogy(moves, np.minimum.accumulate(result.history), label="best so far")
    ax.set_xlabel("annealing move")
    ax.set_ylabel("cost / reference cost")
    ax.legend(fontsize=8)
    ax.set_title("cost history of the winning chain")
    ax.grid(alpha=0.3, which="both")
    fig.suptitle(problem.spec.name)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
