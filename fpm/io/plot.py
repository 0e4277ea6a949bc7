"""Figures of a calibration: deformation profiles (like paper Fig. 5 and 6) and cost history.

The profile of a load case runs along the axis-parallel line through its (first) loaded node
that holds the most nodes (a box: across the loaded face; a voxel organ: often through its
depth), and shows the displacement magnitude of the FEM and the FPM at those nodes. The legend
gives each fit's relative discrepancy over all nodes, ``100 sum_i |p_i - q_i| / sum_i |q_i|``
(p the FPM's, q the FEM's displacement), beside the paper's % of h: the % of h alone shrinks
with soft materials and small loads, so it is never shown alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..dynamics.simulation import simulate
from ..model.problem import Problem
from ..model.stiffness import fitted_theta

if TYPE_CHECKING:
    from matplotlib.figure import Figure

LINE_TOLERANCE = 1e-3
"""A node is on a profile line if its other two coordinates are within this many h of it."""
MIN_LINE_NODES = 3
"""Fewest nodes of an axis-parallel profile line; fewer and the load's own line is used."""
FORCE_LINE_RADIUS = 0.5
"""A node is on the load's own line if it is within this many h of it."""


def profile_line(problem: Problem, load_case: int = 0) -> tuple[np.ndarray, int, int]:
    """The axis-parallel line through the first loaded node that holds the most nodes.

    Ties go to a line across the force (the paper's profiles along the loaded face), then to x
    before y before z. Where no such line holds :data:`MIN_LINE_NODES` nodes (a lattice
    conformed to an organ's surface moves its surface nodes, the loaded ones among them, off
    the grid), the profile runs along the load's own line instead: the nodes within
    :data:`FORCE_LINE_RADIUS` h of the line through the loaded node along the summed force,
    in order along the force's main axis.

    Returns:
        (node indices (P,) sorted along the line, the axis the line runs along (the force's
        main axis on the load's own line), the force's main axis).
    """
    case = problem.load_cases[load_case]
    first = case.nodes[0]
    force = np.asarray(case.forces, dtype=float).sum(axis=0)
    direction = int(np.argmax(np.abs(force)))
    x = problem.nodes
    tol = LINE_TOLERANCE * problem.h
    best, along = np.zeros(0, dtype=np.int64), 0
    for axis in sorted(range(3), key=lambda a: a == direction):
        others = [a for a in range(3) if a != axis]
        line = np.flatnonzero(np.all(np.abs(x[:, others] - x[first, others]) <= tol, axis=1))
        if len(line) > len(best):
            best, along = line, axis
    if len(best) < MIN_LINE_NODES and np.linalg.norm(force) > 0:
        unit = force / np.linalg.norm(force)
        offset = x - x[first]
        across = offset - np.outer(offset @ unit, unit)
        near = np.flatnonzero(np.linalg.norm(across, axis=1) <= FORCE_LINE_RADIUS * problem.h)
        if len(near) > len(best):
            best, along = near, direction
    return best[np.argsort(x[best, along], kind="stable")], along, direction


def relative_discrepancy(fpm: np.ndarray, fem: np.ndarray) -> float:
    """``100 * sum_i |p_i - q_i| / sum_i |q_i|``, % over all nodes, for (N, 3) displacements."""
    size = float(np.linalg.norm(fem, axis=1).sum())
    error = float(np.linalg.norm(fpm - fem, axis=1).sum())
    return 100 * error / size if size > 0 else float("nan")


def calibration_figure(problem: Problem, reference: np.ndarray, result: Any) -> Figure:
    """The figure of :func:`plot_calibration` (profiles | cost history), not saved.

    Args:
        reference: (L, N, 3) FEM displacements, m.
        result: a :class:`fpm.fitting.result.CalibrationResult` (its parameters' k or
            stiffness, d and depth, its settle dt and its run's history; its fit's
            relative_discrepancy and discrepancy_h, % of h, used when present, else computed).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reference = np.asarray(reference, dtype=float)
    fitted = result.parameters
    theta = fitted_theta(problem, fitted)
    relative = _field(result.fit, "relative_discrepancy")
    h_percent = _field(result.fit, "discrepancy_h")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    axes_used = set()
    for j, case in enumerate(problem.load_cases):
        line, along, _ = profile_line(problem, j)
        axes_used.add(along)
        run = simulate(
            problem, k=theta, d=fitted.d, depth=fitted.depth, load_case=j,
            dt=getattr(result.settle, "dt", None),
        )  # fmt: skip
        p, q = run.displacements, reference[j]
        rel = relative[j] if relative is not None else relative_discrepancy(p, q)
        hp = h_percent[j] if h_percent is not None else 100 * _mean_error(p, q) / problem.h
        s = problem.nodes[line, along] * 1e3
        colour = f"C{j}"
        ax.plot(s, np.linalg.norm(q[line], axis=1) * 1e3, "-", color=colour,
                label=f"FEM {case.name} (along {'xyz'[along]})")  # fmt: skip
        ax.plot(s, np.linalg.norm(p[line], axis=1) * 1e3, "o--", color=colour, ms=4,
                label=f"FPM: {rel:.2f}% relative, {hp:.2f}% of h")  # fmt: skip
    if len(axes_used) == 1:
        ax.set_xlabel(f"{'xyz'[axes_used.pop()]} through the loaded node, mm")
    else:
        ax.set_xlabel("position along each load case's line through its loaded node, mm")
    ax.set_ylabel("displacement magnitude, mm")
    ax.set_title(f"{_stiffness_label(fitted)}\nd = {fitted.d:.4g} N s/m, depth {fitted.depth}")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    history = np.asarray(_field(result.run, "history") or [np.nan], dtype=float)
    moves = np.arange(1, len(history) + 1)
    ax.semilogy(moves, history, label="current state")
    ax.semilogy(moves, np.fmin.accumulate(history), label="best so far")
    ax.set_xlabel("annealing move")
    ax.set_ylabel("cost / reference cost")
    ax.legend(fontsize=8)
    ax.set_title("cost history of the winning chain")
    ax.grid(alpha=0.3, which="both")
    fig.suptitle(problem.spec.name)
    fig.tight_layout()
    return fig


def plot_calibration(problem: Problem, reference: np.ndarray, result: Any, out: str | Path) -> None:
    """Save a PNG: per load case the FPM and FEM displacement profiles, and the cost history.

    Args:
        reference: (L, N, 3) FEM displacements, m.
        result: the calibration result (see :func:`calibration_figure`).
    """
    import matplotlib.pyplot as plt

    fig = calibration_figure(problem, reference, result)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _stiffness_label(fitted: Any) -> str:
    """k (or k per family) and kappa of a result's parameters, for the figure's title."""
    stiffness = getattr(fitted, "stiffness", None)
    kappa = getattr(fitted, "volume_stiffness", None)
    volume = "" if kappa is None else f", kappa = {kappa:.4g} Pa"
    if isinstance(stiffness, dict) and len(set(stiffness.values())) > 1:
        springs = ", ".join(f"{v:.4g} ({name})" for name, v in stiffness.items())
        return f"k = {springs} N/m{volume}"
    return f"k = {fitted.k:.4g} N/m{volume}"


def _field(result: Any, *names: str) -> Any:
    """The first of ``names`` the result has (not None), as a list; else None."""
    for name in names:
        value = getattr(result, name, None)
        if value is not None:
            return list(value)
    return None


def _mean_error(p: np.ndarray, q: np.ndarray) -> float:
    return float(np.linalg.norm(p - q, axis=1).mean())
