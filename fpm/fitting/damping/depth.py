"""Depth 'auto': the shortest perturbed list that keeps the fitted model what it is. A depth
passes when in every load case its cost is within (1 + tolerance) of full depth's (the cost
test) and the model's own linear response to the case's forces turned along x, y and z changes
by at most tolerance times the case's relative discrepancy (the response test); the smallest
that passes is found by galloping down from full depth, then bisecting
(docs/explanation/physics/calibration-paper-depth.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...dynamics.simulation import fpm_model
from ...fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ...model.forces import Stiffness
from ...model.stiffness import model_stiffness
from ..bounds import full_depth
from ..cost import StaticCost
from ..stiffness_stage import Progress


def resolve_depth(
    cost: StaticCost, theta: list[float], tolerance: float, progress: Progress | None = None
) -> tuple[int, int, dict[int, list[float]]]:
    """Depth 'auto' at the stiffness ``theta`` fitted at full depth, with ``tolerance``
    (relative). Returns (depth, full depth, {depth probed: case costs, m}; none where the
    response test's bound refused it); full depth where it has no finite cost."""
    full = cost(theta, None)
    deepest = full_depth(cost.problem)
    probed: dict[int, list[float]] = {deepest: full.case_costs}
    if not math.isfinite(full.cost):  # no equilibrium at full depth: nothing to cut against
        return deepest, deepest, probed
    stiffness = model_stiffness(cost.problem, theta)
    # each probe starts from full depth's equilibria (a warm solve returns them as they are)
    cases = range(len(cost.problem.load_cases))
    shapes = [cost.displacements(theta, j, None).displacements for j in cases]
    responses = OwnResponses.at_full_depth(cost, stiffness, full.case_costs, tolerance)

    def passes(depth: int) -> bool:
        if progress is not None:
            progress({"phase": "depth", "depth": depth})
        if responses is not None and not responses.may_keep(depth):
            probed[depth] = []
            return False
        for j, u in enumerate(shapes):
            cost.solver.seed(j, stiffness, depth, u)
        ev = cost(theta, depth)
        probed[depth] = ev.case_costs
        if not math.isfinite(ev.cost) or any(
            c > f * (1 + tolerance) for c, f in zip(ev.case_costs, full.case_costs, strict=True)
        ):
            return False
        return responses is None or responses.keeps(depth)

    fail, ok, gap = -1, deepest, 1
    while ok - gap > fail:
        if not passes(ok - gap):
            fail = ok - gap
            break
        ok, gap = ok - gap, 2 * gap
    while ok - fail > 1:
        mid = (fail + ok) // 2
        if passes(mid):
            ok = mid
        else:
            fail = mid
    return ok, deepest, probed


@dataclass
class _Pattern:
    """The load cases that share one force pattern: the first of them (its list and solver
    systems), the nodal force magnitudes (N,) N, the response along each axis at full depth
    ((3, N, 3) m), each node's layer in the full list (N,; -1 off it), the allowance (the
    smallest of its cases': a relative change) and the changes measured so far by depth."""

    case: int
    magnitudes: np.ndarray
    full: np.ndarray
    layer: np.ndarray
    allowed: float
    changes: dict[int, float] = field(default_factory=dict)

    def beyond(self, depth: int) -> float:
        """The largest share, over the axes, of full depth's response on nodes beyond
        ``depth`` (a lower bound of the change at that depth)."""
        out = (self.layer > depth) | (self.layer < 0)
        lengths = np.linalg.norm(self.full, axis=2)  # (3, N)
        return float(max(lengths[a, out].sum() / lengths[a].sum() for a in range(3)))


class OwnResponses:
    """The response test of depth 'auto' (module docstring) on one :class:`StaticCost`'s
    solver (not thread-safe, as the solver)."""

    def __init__(self, cost: StaticCost, stiffness: Stiffness, patterns: list[_Pattern]):
        self.cost = cost
        self.stiffness = stiffness
        self.patterns = patterns

    @classmethod
    def at_full_depth(
        cls, cost: StaticCost, stiffness: Stiffness, case_costs: list[float], tolerance: float
    ) -> OwnResponses | None:
        """The full-depth responses of every distinct force pattern, the allowances from the
        cases' costs at full depth (m); None where the lattice at rest has no linear response
        (a mechanism) or a cost is not finite."""
        problem = cost.problem
        if len(case_costs) != len(problem.load_cases) or not all(map(math.isfinite, case_costs)):
            return None
        model = fpm_model(problem)
        found: dict[bytes, _Pattern] = {}
        for j, case in enumerate(problem.load_cases):
            size = float(np.linalg.norm(cost.reference[j], axis=1).sum())
            allowed = tolerance * case_costs[j] / size if size > 0 else math.inf
            magnitudes = np.linalg.norm(case.dense(problem.n_nodes), axis=1)
            key = np.round(magnitudes / magnitudes.max(), 12).tobytes()
            if key in found:
                found[key].allowed = min(found[key].allowed, allowed)
                continue
            listed = model.perturbed_list(j, None)
            layer = np.full(problem.n_nodes, -1)
            for i in range(listed.layers + 1):
                layer[listed.layer(i)] = i
            try:
                full = np.stack(cls._solve(cost, stiffness, j, None, magnitudes, None))
            except (SingularStiffnessError, NegativeCurvature):
                return None
            found[key] = _Pattern(j, magnitudes, full, layer, allowed)
        return cls(cost, stiffness, list(found.values()))

    def may_keep(self, depth: int) -> bool:
        """Whether ``depth`` can pass: no pattern's response beyond it exceeds its allowance."""
        return all(p.beyond(depth) <= p.allowed for p in self.patterns)

    def keeps(self, depth: int) -> bool:
        """Whether every pattern's response at ``depth`` is within its allowance of full
        depth's (three linear solves per pattern, each started from full depth's answer)."""
        for p in self.patterns:
            if depth not in p.changes:
                solved = self._solve(self.cost, self.stiffness, p.case, depth, p.magnitudes, p.full)
                p.changes[depth] = max(_relative(u, f) for u, f in zip(solved, p.full, strict=True))
            if p.changes[depth] > p.allowed:
                return False
        return True

    @staticmethod
    def _solve(
        cost: StaticCost,
        stiffness: Stiffness,
        j: int,
        depth: int | None,
        magnitudes: np.ndarray,
        guesses: np.ndarray | None,
    ) -> list[np.ndarray]:
        """Load case ``j``'s list at ``depth`` linearised at rest under ``magnitudes`` (N,) N
        along x, y and z: three (N, 3) displacements, m (one tangent for the three)."""
        solver = cost.solver
        system, _ = solver.system(j, depth)
        tangent = system.tangent(
            np.zeros((system.n_free, 3)), system.parameters(Stiffness.of(stiffness)), modified=True
        )
        out = []
        for a in range(3):
            loads = np.zeros((len(magnitudes), 3))
            loads[:, a] = magnitudes
            guess = None if guesses is None else guesses[a]
            out.append(solver.linear_solve(j, depth, tangent, loads, guess=guess))
        return out


def _relative(u: np.ndarray, full: np.ndarray) -> float:
    """sum_i |u_i - full_i| / sum_i |full_i| (Eq. 2's norm; (N, 3) arrays)."""
    return float(np.linalg.norm(u - full, axis=1).sum() / np.linalg.norm(full, axis=1).sum())
