"""FPM simulation of one load case (paper Sec. 3.2): the Python API around the compiled step."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .perturbed_list import Adjacency, PerturbedList, PerturbedListCache
from .problem import Problem
from .spec import FpmSettings
from .stiffness import axis_factors, spring_stiffness
from .voigt import DIVERGED, SETTLED, run_steps


@dataclass
class SimulationResult:
    """Outcome of one FPM run of one load case.

    Attributes:
        nodes: (N, 3) rest positions, m.
        displacements: (N, 3) final displacements, m (zero outside the perturbed list).
        steps: time steps taken.
        settled: the run reached equilibrium within max_steps (physics.md criterion).
        diverged: positions became non-finite or moved further than the solid's size.
        perturbed: number of nodes in the perturbed list.
        depth: layers actually reached (<= the depth asked for).
        residual: largest unbalanced nodal force |F_i + F_s| in the last sweep, N.
        load_case: index of the load case.
    """

    nodes: np.ndarray
    displacements: np.ndarray
    steps: int
    settled: bool
    diverged: bool
    perturbed: int
    depth: int
    residual: float
    load_case: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (arrays as nested lists)."""
        out = asdict(self)
        out["nodes"] = self.nodes.tolist()
        out["displacements"] = self.displacements.tolist()
        return out


class FpmModel:
    """A problem's FPM arrays, built once: neighbours, perturbed lists, work buffers.

    Attributes:
        problem: the problem.
        adjacency: spring neighbours (:class:`fpm.perturbed_list.Adjacency`).
        lists: the perturbed-list lookup table.
    """

    def __init__(self, problem: Problem):
        self.problem = problem
        solid = problem.solid
        self.adjacency = Adjacency.from_springs(
            len(solid.nodes), solid.springs, problem.rest_lengths, axis_factors(problem)
        )
        self.lists = PerturbedListCache(self.adjacency, problem.fixed)
        self._x = np.empty_like(solid.nodes)
        self._v = np.empty_like(solid.nodes)
        gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
        self._weight = solid.masses[:, None] * gravity[None, :] if np.any(gravity) else None

    def perturbed_list(self, load_case: int, depth: int | None) -> PerturbedList:
        """The (cached) list of ``load_case`` for ``depth`` layers (None = all reachable)."""
        return self.lists.get(self.problem.load_cases[load_case].nodes, depth)

    def run(
        self,
        load_case: int,
        *,
        k: float | np.ndarray,
        d: float,
        depth: int | None,
        dt: float,
        max_steps: int,
        settle_tolerance: float,
    ) -> SimulationResult:
        """Simulate ``load_case`` from rest; see :func:`simulate`.

        ``k`` is one stiffness for every spring (scaled by the spec's stiffness_scale), N/m, or
        the (S,) stiffness of every spring (:func:`fpm.stiffness.spring_stiffness`, scale
        included).
        """
        p = self.problem
        case = p.load_cases[load_case]
        plist = self.perturbed_list(load_case, depth)
        external = case.dense(p.n_nodes)
        if self._weight is not None:
            external += self._weight
        settle_force = settle_tolerance * float(np.linalg.norm(external[plist.order], axis=1).max())
        x, v = self._x, self._v
        x[:] = p.nodes
        v[:] = 0.0
        a = self.adjacency
        factor = a.stiffness_factor
        if np.ndim(k):  # per-spring stiffness: the kernel's factor carries it, with k = 1
            factor, k = np.asarray(k, dtype=float)[a.spring], 1.0
        steps, state, residual = run_steps(
            plist.order, a.ptr, a.neighbour, a.rest_length, factor, p.nodes,
            x, v, external, p.solid.masses, float(k), float(d), float(dt), int(max_steps),
            settle_force, p.size,
        )  # fmt: skip
        return SimulationResult(
            nodes=p.nodes,
            displacements=x - p.nodes,
            steps=int(steps),
            settled=state == SETTLED,
            diverged=state == DIVERGED,
            perturbed=len(plist.order),
            depth=plist.layers,
            residual=float(residual),
            load_case=load_case,
        )


def fpm_model(problem: Problem) -> FpmModel:
    """The problem's :class:`FpmModel`, built on first use and kept on the problem."""
    model = problem.cache.get("fpm_model")
    if model is None:
        model = problem.cache["fpm_model"] = FpmModel(problem)
    return model


def simulate(
    problem: Problem,
    *,
    k: float | Sequence[float],
    d: float,
    depth: int | None = None,
    load_case: int = 0,
    dt: float | None = None,
    max_steps: int | None = None,
    settle_tolerance: float | None = None,
) -> SimulationResult:
    """Run the FPM for one load case from rest.

    Args:
        problem: from :func:`fpm.load_problem`.
        k: spring stiffness, N/m: one value for every spring, or one per spring family
            (:mod:`fpm.stiffness`).
        d: nodal damping, N s/m.
        depth: penetration depth in layers; None = the spec's (its 'auto' means all layers).
        load_case: index into the spec's load cases.
        dt, max_steps, settle_tolerance: None = the spec's value; ``settle_tolerance=0`` never
            settles.
    """
    s = problem.spec.fpm
    if not 0 <= load_case < len(problem.load_cases):
        raise ValueError(f"load_case must be in 0..{len(problem.load_cases) - 1}")
    if not (np.all(np.asarray(k) > 0) and d >= 0):
        raise ValueError("need k > 0 and d >= 0")
    stiffness: float | np.ndarray = (
        spring_stiffness(problem, k) if np.ndim(k) else float(k)  # type: ignore[arg-type]
    )
    if depth is None and s.depth != "auto":
        depth = int(s.depth)
    # Overrides pass the schema's own checks (dt > 0, max_steps >= 1, depth >= 0, ...).
    given = {"dt": dt, "max_steps": max_steps, "settle_tolerance": settle_tolerance}
    if depth is not None:
        given["depth"] = depth
    settings = FpmSettings.model_validate(
        s.model_dump() | {key: v for key, v in given.items() if v is not None}
    )
    return fpm_model(problem).run(
        load_case,
        k=stiffness,
        d=d,
        depth=depth,
        dt=settings.dt,
        max_steps=settings.max_steps,
        settle_tolerance=settings.settle_tolerance,
    )
