"""The cost of paper Eq. (2) and the figures of merit of a fit.

``c = sum over load cases j, sum over ALL nodes i of |p_i - q_i|`` where p is the FPM's final
position and q the FEM's (nodes the FPM did not move count with their full FEM displacement).

Two ways to get p: :class:`CostFunction` runs the FPM dynamically to rest at (stiffness, d)
(the paper's); :class:`StaticCost` solves for the settled state directly
(:mod:`fpm.dynamics.equilibrium`), which does not depend on d. Figures of merit per load case
(:func:`discrepancies`): the relative discrepancy (the headline: scale-free), the error at the
loaded nodes relative to their FEM displacement, the mean nodal discrepancy in % of h (the
paper's unit, which shrinks with soft materials and small loads, so never shown alone), and the
load compliance ratio (:func:`compliance_ratio`: how soft the model feels under the load).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..dynamics.settle import SettleCriterion, force_tolerance
from ..dynamics.simulation import FpmModel
from ..dynamics.step_caps import fixed_max_steps
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.stiffness import model_stiffness
from .bounds import stiffness_bounds

Theta = float | Sequence[float] | np.ndarray | Stiffness
"""Stiffness parameters: k, or one k per spring family (N/m), then kappa (Pa) for
families+volume (:mod:`fpm.model.stiffness`); or the model's Stiffness itself (a field's)."""


@dataclass
class Evaluation:
    """The FPM at one parameter point against the reference, over all load cases.

    Attributes:
        cost: Eq. (2), m (inf if a load case diverged, did not settle when asked to stop, or
            had no equilibrium).
        case_costs: (L,) per load case, m.
        steps: (L,) time steps (dynamic) or Newton iterations (static) per load case.
        settled: every load case settled (dynamic) or converged (static).
        diverged: some load case diverged (the remaining ones were not run).
        rejected: why the cost is inf: "diverged", "unsettled", "no equilibrium", or "".
    """

    cost: float
    case_costs: list[float]
    steps: list[int]
    settled: bool
    diverged: bool
    rejected: str = ""


@dataclass
class Discrepancies:
    """How well FPM displacements match the FEM's, per load case.

    Attributes:
        relative: 100 * sum_i |p_i - q_i| / sum_i |q_i - q0_i|, % (the headline figure).
        loaded: the same over the loaded nodes only, %.
        h_percent: mean nodal |p_i - q_i| over all nodes, % of h (the paper's unit).
        compliance: the load compliance ratio (:func:`compliance_ratio`): how soft the loaded
            nodes feel beside the reference (1: as stiff; above 1 softer), None where undefined.
    """

    relative: list[float] = field(default_factory=list)
    loaded: list[float] = field(default_factory=list)
    h_percent: list[float] = field(default_factory=list)
    compliance: list[float | None] = field(default_factory=list)


def compliance_ratio(
    nodes: np.ndarray, forces: np.ndarray, fpm: np.ndarray, reference: np.ndarray
) -> float | None:
    """The load compliance ratio of one load case: ``sum_i f_i . u_i`` over its loaded nodes
    ``nodes`` (P,) with forces ``forces`` (P, 3), N, for the model's displacements ``fpm``
    (N, 3), m, over the same for the reference's ``reference`` (N, 3), m (the work the load
    does on each). 1: a probe at those nodes feels the reference's stiffness; 1.5: the model
    is 1.5 times too soft there; 0.8: 1.25 times too stiff. Scale-free: the same for forces
    and displacements scaled together. None when the load does no work on the reference
    (forces across its displacements), where no ratio is defined."""
    f = np.asarray(forces, dtype=float)
    model = float(np.einsum("ij,ij->", f, fpm[nodes]))
    truth = float(np.einsum("ij,ij->", f, reference[nodes]))
    if not truth > 0:
        return None
    return model / truth


def discrepancies(problem: Problem, fpm: np.ndarray, reference: np.ndarray) -> Discrepancies:
    """Figures of merit of FPM displacements ``fpm`` (L, N, 3) against ``reference`` (L, N, 3)."""
    out = Discrepancies()
    for j, case in enumerate(problem.load_cases):
        error = np.linalg.norm(fpm[j] - reference[j], axis=1)
        size = np.linalg.norm(reference[j], axis=1)
        out.relative.append(float(100 * error.sum() / size.sum()))
        out.loaded.append(float(100 * error[case.nodes].sum() / size[case.nodes].sum()))
        out.h_percent.append(float(100 * error.mean() / problem.h))
        out.compliance.append(compliance_ratio(case.nodes, case.forces, fpm[j], reference[j]))
    return out


class _Reference:
    """Checks and holds (L, N, 3) reference displacements, m."""

    def __init__(self, problem: Problem, reference: np.ndarray, depth: int | None):
        self.problem = problem
        self.reference = np.asarray(reference, dtype=float)
        if self.reference.shape != (len(problem.load_cases), problem.n_nodes, 3):
            raise ValueError(
                f"reference displacements have shape {self.reference.shape}, expected "
                f"{(len(problem.load_cases), problem.n_nodes, 3)}"
            )
        self.depth = depth
        self.evaluations = 0
        self.reference_cost = float(np.linalg.norm(self.reference, axis=2).sum())
        """Cost of an FPM that does not move at all: the natural unit of cost."""

    def case_cost(self, j: int, displacements: np.ndarray) -> float:
        return float(np.linalg.norm(displacements - self.reference[j], axis=1).sum())


def dynamic_time_step(problem: Problem) -> float:
    """The paper method's dt, s: the spec's, or for 'auto' the auto dt at the top of the
    stiffness bounds (one dt for every candidate of the joint (k, d) search, stable for all)."""
    from ..dynamics.stability import time_step

    return time_step(problem, model_stiffness(problem, stiffness_bounds(problem)[1]))


class CostFunction(_Reference):
    """Eq. (2) from dynamic FPM runs, counting its evaluations.

    Args:
        problem: the problem.
        reference: (L, N, 3) FEM displacements, m, one per load case in spec order.
        depth: penetration depth (None = every layer reachable).
        dt: time step, s; None = :func:`dynamic_time_step`.
    """

    def __init__(
        self, problem: Problem, reference: np.ndarray, depth: int | None, dt: float | None = None
    ):
        super().__init__(problem, reference, depth)
        self.model = FpmModel(problem)  # own buffers: one cost function per thread
        self.dt = dynamic_time_step(problem) if dt is None else float(dt)

    def displacements(
        self,
        theta: Theta,
        d: float,
        load_case: int,
        depth: int | None = None,
        max_steps: int | None = None,
    ):
        """The FPM run of one load case (depth None = this cost function's depth)."""
        s = self.problem.spec.fpm
        return self.model.run(
            load_case,
            k=model_stiffness(self.problem, theta),
            d=d,
            depth=self.depth if depth is None else depth,
            dt=self.dt,
            max_steps=fixed_max_steps(s.max_steps) if max_steps is None else max_steps,
            settle=SettleCriterion(force_tolerance=force_tolerance(self.problem.spec)),
        )

    def __call__(self, theta: Theta, d: float, *, stop_unsettled: bool = False) -> Evaluation:
        """Eq. (2) at (theta, d); ``stop_unsettled`` skips the remaining load cases (cost inf)
        once one has not settled, for a caller that rejects unsettled states anyway."""
        self.evaluations += 1
        costs: list[float] = []
        steps: list[int] = []
        settled = True
        for j in range(len(self.problem.load_cases)):
            run = self.displacements(theta, d, j)
            steps.append(run.steps)
            if run.diverged:
                return Evaluation(float("inf"), costs, steps, False, True, "diverged")
            costs.append(self.case_cost(j, run.displacements))
            settled &= run.settled
            if not run.settled and stop_unsettled:
                return Evaluation(float("inf"), costs, steps, False, False, "unsettled")
        return Evaluation(float(sum(costs)), costs, steps, settled, False)


class StaticCost(_Reference):
    """Eq. (2) from static equilibria (:class:`fpm.dynamics.equilibrium.StaticSolver`): no d, no dt.

    One instance per thread (the solver keeps warm starts and preconditioners).
    """

    def __init__(self, problem: Problem, reference: np.ndarray, depth: int | None):
        from ..dynamics.equilibrium import StaticSolver

        super().__init__(problem, reference, depth)
        self.solver = StaticSolver(problem)

    def displacements(self, theta: Theta, load_case: int, depth: int | None = None):
        """The equilibrium of one load case (depth None = this cost function's depth)."""
        return self.solver.solve(
            load_case,
            model_stiffness(self.problem, theta),
            self.depth if depth is None else depth,
        )

    def __call__(self, theta: Theta, depth: int | None = None) -> Evaluation:
        """Eq. (2) at ``theta`` (depth None = this cost function's)."""
        self.evaluations += 1
        costs: list[float] = []
        steps: list[int] = []
        for j in range(len(self.problem.load_cases)):
            eq = self.displacements(theta, j, depth)
            steps.append(eq.iterations)
            if not eq.converged:
                return Evaluation(float("inf"), costs, steps, False, False, "no equilibrium")
            costs.append(self.case_cost(j, eq.displacements))
        return Evaluation(float(sum(costs)), costs, steps, True, False)
