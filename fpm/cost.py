"""The cost of paper Eq. (2) and the paper's figure of merit, the mean nodal discrepancy.

``c = sum over load cases j, sum over ALL nodes i of |p_i - q_i|`` where p is the FPM's final
position and q the FEM's (nodes the FPM did not move count with their full FEM displacement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .problem import Problem
from .simulation import FpmModel


@dataclass
class Evaluation:
    """The FPM at one (k, d) against the reference, over all load cases.

    Attributes:
        cost: Eq. (2), m (inf if a load case diverged, or did not settle when asked to stop).
        case_costs: (L,) per load case, m.
        steps: (L,) time steps per load case.
        settled: every load case settled.
        diverged: some load case diverged (the remaining ones were not run).
    """

    cost: float
    case_costs: list[float]
    steps: list[int]
    settled: bool
    diverged: bool


class CostFunction:
    """Eq. (2) for a problem against its reference displacements, counting its evaluations.

    Args:
        problem: the problem.
        reference: (L, N, 3) FEM displacements, m, one per load case in spec order.
        depth: penetration depth (None = every layer reachable).
    """

    def __init__(self, problem: Problem, reference: np.ndarray, depth: int | None):
        self.problem = problem
        self.reference = np.asarray(reference, dtype=float)
        if self.reference.shape != (len(problem.load_cases), problem.n_nodes, 3):
            raise ValueError(
                f"reference displacements have shape {self.reference.shape}, expected "
                f"{(len(problem.load_cases), problem.n_nodes, 3)}"
            )
        self.depth = depth
        self.model = FpmModel(problem)  # own buffers: one cost function per thread
        self.evaluations = 0
        self.reference_cost = float(np.linalg.norm(self.reference, axis=2).sum())
        """Cost of an FPM that does not move at all: the natural unit of cost."""

    def displacements(self, k: float, d: float, load_case: int, depth: int | None = None):
        """The FPM run of one load case (depth None = this cost function's depth)."""
        s = self.problem.spec.fpm
        return self.model.run(
            load_case,
            k=k,
            d=d,
            depth=self.depth if depth is None else depth,
            dt=s.dt,
            max_steps=s.max_steps,
            settle_tolerance=s.settle_tolerance,
        )

    def __call__(self, k: float, d: float, *, stop_unsettled: bool = False) -> Evaluation:
        """Eq. (2) at (k, d); ``stop_unsettled`` skips the remaining load cases (cost inf)
        once one has not settled, for a caller that rejects unsettled states anyway."""
        self.evaluations += 1
        costs: list[float] = []
        steps: list[int] = []
        settled = True
        for j in range(len(self.problem.load_cases)):
            run = self.displacements(k, d, j)
            steps.append(run.steps)
            if run.diverged:
                return Evaluation(float("inf"), costs, steps, False, True)
            costs.append(float(np.linalg.norm(run.displacements - self.reference[j], axis=1).sum()))
            settled &= run.settled
            if not run.settled and stop_unsettled:
                return Evaluation(float("inf"), costs, steps, False, False)
        return Evaluation(float(sum(costs)), costs, steps, settled, False)

    def discrepancy(self, k: float, d: float, depth: int | None = None) -> list[float]:
        """Mean nodal discrepancy |p_i - q_i| over all nodes, in % of h, per load case."""
        out = []
        for j in range(len(self.problem.load_cases)):
            u = self.displacements(k, d, j, depth).displacements
            out.append(
                float(np.linalg.norm(u - self.reference[j], axis=1).mean() / self.problem.h * 100)
            )
        return out
