"""The static equilibrium of the FPM: the state a settled dynamic run reaches, found directly.

A settled run's state does not depend on the damping d (docs/physics.md, *Static
equilibrium*): it is the minimum, over the displacements u_i of the perturbed-list nodes, of
the springs' energy minus the work of the constant nodal forces,

    E(u) = sum_s 1/2 k_s (|r_s| - L_s)^2 - sum_i F_i . u_i,     r_s = x_j - x_i,  x = X + u,

nodes outside the list and fixed nodes held at their rest positions X; F_i the load case's
nodal forces plus the node weight m_i g when the spec's gravity is non-zero. The springs are
geometrically nonlinear (they rotate and stretch), so E is minimised by Newton's method:

- E, its gradient (minus the unbalanced nodal force F_i + F_s of the dynamic run) and its
  tangent, with the cells' volume term when the model has one:
  :class:`~fpm.dynamics.spring_system.SpringSystem` (:mod:`fpm.dynamics.spring_system`, the
  cells' loops in :mod:`fpm.dynamics.cell_terms`);
- Newton steps (:mod:`fpm.dynamics.newton`): each tries the exact tangent first; where it is
  not positive definite the step is redone with the factor (1 - L/|r|) clamped at 0, a positive
  semi-definite tangent whose steps always descend; where that is singular (a mechanism), with
  a small diagonal shift. A backtracking (Armijo) line search on E makes every step decrease it;
- linear solves (:mod:`fpm.dynamics.linear_solves`): sparse LU below
  :data:`~fpm.dynamics.linear_solves.AMG_FROM_UNKNOWNS` unknowns; above, conjugate gradients
  preconditioned by a multigrid hierarchy kept across Newton steps, stiffness changes, load
  cases and calls while CG converges at its first rate; inexact Newton (Eisenstat-Walker);
- warm starts (:mod:`fpm.dynamics.predictor`): converged solutions kept per (load case,
  list) predict where Newton starts, refined on a Galerkin reduced model; on an annealing
  walk with one k most solves then need no Newton step at all (full depth asked as None and
  as its number is one list: the second solve at the same stiffness takes none).

Converged when the largest unbalanced nodal force over the list is at most ``tolerance`` times
the largest applied nodal force (the settle criterion of the dynamic run, with a tenth of its
tolerance by default, so the static answer is at least as converged as a settled run).

Thread-safety: a :class:`StaticSolver` keeps mutable caches (warm starts, multigrid
hierarchies, its tangent buffers) and is not thread-safe; use one per thread.
:func:`static_equilibrium` does so: it keeps one solver per thread on the problem. What only
depends on the problem, its perturbed lists and spring systems, is read only and shared by its
solvers (:func:`~fpm.dynamics.spring_system.spring_lists`,
:func:`~fpm.dynamics.spring_system.shared_system`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..fem.linear_solver import ReusedHierarchy
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.stiffness import model_stiffness
from .linear_solves import AMG_FROM_UNKNOWNS, LinearSolves
from .newton import Newton
from .predictor import _Predictor, _Stats
from .settle import force_tolerance
from .spring_system import SpringSystem, shared_system, spring_lists

MAX_SYSTEMS = 6
"""Spring systems (distinct perturbed lists) a solver keeps, with their multigrid hierarchies
and warm starts."""


class EquilibriumError(RuntimeError):
    """A static solve that did not converge (raised by :meth:`Equilibrium.check`)."""


@dataclass
class Equilibrium:
    """The static equilibrium of one load case.

    Attributes:
        displacements: (N, 3) nodal displacements, m (zero outside the perturbed list).
        iterations: Newton iterations taken.
        linear_iterations: CG iterations over all Newton steps (0 when solved by LU).
        residual: largest unbalanced nodal force |F_i + F_s| over the list nodes, N.
        converged: residual <= tolerance * largest applied nodal force (and no node moved
            further than the solid's size, where a dynamic run would stop as diverged).
        perturbed: number of nodes in the perturbed list (the free nodes).
        depth: layers the list reached (<= the depth asked for).
        load_case: index of the load case.
        tolerance: the relative tolerance solved to.
        message: why the solve stopped, when it did not converge ("" otherwise).
        start: where Newton started: "rest", or "predicted" from earlier solutions.
        seconds: wall time of the solve, s.
    """

    displacements: np.ndarray
    iterations: int
    linear_iterations: int
    residual: float
    converged: bool
    perturbed: int
    depth: int
    load_case: int
    tolerance: float = 0.0
    message: str = ""
    start: str = "rest"
    seconds: float = 0.0

    def check(self) -> Equilibrium:
        """Return self if converged, else raise :class:`EquilibriumError` with the message."""
        if not self.converged:
            raise EquilibriumError(self.message or "static equilibrium did not converge")
        return self


class StaticSolver(Newton, LinearSolves):
    """Static equilibria of one problem's load cases, with everything worth keeping between
    calls: perturbed lists, spring systems, multigrid hierarchies and warm starts.

    Not thread-safe (warm starts and hierarchies are updated by every solve): use one per thread.
    ``hierarchies_built`` counts the multigrid hierarchies built so far.

    Args:
        problem: the problem.
        amg_from: free unknowns from which Newton steps use multigrid CG rather than LU
            (default :data:`AMG_FROM_UNKNOWNS`; 0 forces CG, a huge value forces LU).
        warm: start from earlier solutions of the same (load case, depth) (see
            :class:`_Predictor`); False = always from rest.
    """

    def __init__(self, problem: Problem, *, amg_from: int | None = None, warm: bool = True):
        self.problem = problem
        self.amg_from = AMG_FROM_UNKNOWNS if amg_from is None else int(amg_from)
        self.warm = warm
        solid = problem.solid
        self.lists = spring_lists(problem)
        gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
        self._weight = solid.masses[:, None] * gravity[None, :] if np.any(gravity) else None
        self._lists: dict[tuple[int, int | None], tuple[bytes, np.ndarray, int]] = {}
        self._systems: dict[bytes, SpringSystem] = {}
        self._buffers: dict[bytes, np.ndarray] = {}  # per system: the Newton tangent's values
        self._multigrid: dict[bytes, ReusedHierarchy] = {}
        # warm starts per (load case, list): depths whose lists hold the same nodes (full
        # depth asked as None and as its number) share them
        self._predictors: dict[tuple[int, bytes], _Predictor] = {}
        self.hierarchies_built = 0

    def default_tolerance(self) -> float:
        """A tenth of the force criterion's settle tolerance (1e-6 where the spec names none,
        :func:`fpm.dynamics.settle.force_tolerance`; 1e-8 if it is 0)."""
        settle = force_tolerance(self.problem.spec)
        return settle / 10 if settle > 0 else 1e-8

    def system(self, load_case: int, depth: int | None) -> tuple[SpringSystem, int]:
        """The (cached) spring system of ``load_case``'s list at ``depth`` layers (None = all),
        and the layers that list reached.

        Lists with the same nodes share one system (and one multigrid hierarchy); the
        :data:`MAX_SYSTEMS` most recently used are kept, with their hierarchies and warm starts.
        """
        key, free, layers = self._list(load_case, depth)
        system = self._systems.pop(key, None)
        if system is None:
            system = shared_system(self.problem, free)
        self._systems[key] = system  # the most recently used last
        while len(self._systems) > MAX_SYSTEMS:
            self._drop(next(iter(self._systems)))
        return system, layers

    def _list(self, load_case: int, depth: int | None) -> tuple[bytes, np.ndarray, int]:
        """(its key, its free nodes ascending, the layers it reached) of ``load_case``'s list
        at ``depth`` layers (None = all)."""
        case = (load_case, depth)
        found = self._lists.get(case)
        if found is None:
            plist = self.lists.get(self.problem.load_cases[load_case].nodes, depth)
            free = np.sort(plist.order).astype(np.int64)
            found = self._lists[case] = (free.tobytes(), free, plist.layers)
        return found

    def _drop(self, key: bytes) -> None:
        """Forget the system of list ``key`` with its tangent buffer, hierarchy and warm starts."""
        del self._systems[key]
        self._buffers.pop(key, None)
        self._multigrid.pop(key, None)
        for warm in [c for c in self._predictors if c[1] == key]:
            del self._predictors[warm]

    def keep_only(self, depth: int | None) -> None:
        """Forget every system (with its hierarchy and warm starts) that no load case's list at
        ``depth`` uses: the depth search's probes, once the depth is chosen. Solves at
        ``depth`` are unchanged to the bit: their systems and warm starts stay."""
        wanted = {self._list(j, depth)[0] for j in range(len(self.problem.load_cases))}
        for key in [k for k in self._systems if k not in wanted]:
            self._drop(key)

    def seed(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        displacements: np.ndarray,
    ) -> None:
        """Keep ``displacements`` (N, 3), m, as a warm start of ``load_case``'s list at
        ``depth``, as if found at ``stiffness``: an equilibrium solved elsewhere (a chain's
        last, in another process), or a deeper list's restricted to this one (a start only:
        every answer is still checked against the residual, and a start worse than rest is
        not taken). Nothing is kept when warm starts are off."""
        if not self.warm:
            return
        system, _ = self.system(load_case, depth)
        k = system.parameters(Stiffness.of(stiffness))
        case = (load_case, system.free.tobytes())
        predictor = self._predictors.setdefault(case, _Predictor(len(k.flat)))
        predictor.add(np.asarray(displacements, dtype=float)[system.free], k.flat)

    def loads(self, load_case: int) -> np.ndarray:
        """(N, 3) constant nodal forces, N: the load case's plus the weight."""
        external = self.problem.load_cases[load_case].dense(self.problem.n_nodes)
        if self._weight is not None:
            external += self._weight
        return external

    def forces(self, load_case: int, system: SpringSystem) -> np.ndarray:
        """(M, 3) constant nodal forces on the free nodes, N (load case plus weight)."""
        return self.loads(load_case)[system.free]

    def solve(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        *,
        tolerance: float | None = None,
    ) -> Equilibrium:
        """The static equilibrium of ``load_case``.

        Args:
            load_case: index into the problem's load cases.
            stiffness: the model's :class:`~fpm.model.forces.Stiffness`
                (:func:`fpm.model.stiffness.model_stiffness`), or (S,) stiffness of every
                spring, N/m, for a model without the volume term.
            depth: layers of the perturbed list; None = all reachable.
            tolerance: converged when the largest unbalanced nodal force is at most this times
                the largest applied nodal force; None = :meth:`default_tolerance`.
        """
        start = time.perf_counter()
        p = self.problem
        if not 0 <= load_case < len(p.load_cases):
            raise ValueError(f"load_case must be in 0..{len(p.load_cases) - 1}")
        stiffness = Stiffness.of(stiffness)
        if stiffness.springs.shape != (len(p.solid.springs),):
            raise ValueError(f"need one stiffness per spring, shape ({len(p.solid.springs)},)")
        if not np.all(stiffness.springs > 0):
            raise ValueError("need every spring stiffness > 0")
        if stiffness.volume is not None and not np.all(stiffness.volume >= 0):
            raise ValueError("need every volume stiffness >= 0")
        tol = self.default_tolerance() if tolerance is None else float(tolerance)
        if not tol > 0:
            raise ValueError("need tolerance > 0")
        system, layers = self.system(load_case, depth)
        forces = self.forces(load_case, system)
        k = system.parameters(stiffness)
        applied = float(np.sqrt(np.einsum("ij,ij->i", forces, forces)).max(initial=0.0))
        target = tol * applied
        stats = _Stats()
        case = (load_case, system.free.tobytes())
        predictor = self._predictors.get(case)
        if predictor is None:
            predictor = self._predictors[case] = _Predictor(len(k.flat))
        u, gradient = self._start(predictor, system, k, forces, applied, target, stats)
        u, residual, converged = self._newton(system, k, forces, u, gradient, target, stats)
        if converged and self.warm:
            predictor.add(u, k.flat)
        displacements = np.zeros_like(p.nodes)
        displacements[system.free] = u
        return Equilibrium(
            displacements=displacements,
            iterations=stats.iterations,
            linear_iterations=stats.linear_iterations,
            residual=residual,
            converged=converged,
            perturbed=system.n_free,
            depth=layers,
            load_case=load_case,
            tolerance=tol,
            message=stats.message,
            start=stats.start,
            seconds=time.perf_counter() - start,
        )


_SOLVERS = threading.Lock()


def static_solver(problem: Problem) -> StaticSolver:
    """This thread's :class:`StaticSolver` of ``problem``, built on first use and kept on the
    problem (``problem.cache.static_solvers``, one per thread)."""
    local = problem.cache.static_solvers
    if local is None:
        with _SOLVERS:
            local = problem.cache.static_solvers
            if local is None:
                local = problem.cache.static_solvers = threading.local()
    solver = getattr(local, "solver", None)
    if solver is None:
        solver = local.solver = StaticSolver(problem)
    return solver


def static_equilibrium(
    problem: Problem,
    *,
    k: float | Sequence[float] | np.ndarray | Stiffness,
    depth: int | None = None,
    load_case: int = 0,
    tolerance: float | None = None,
) -> Equilibrium:
    """The static equilibrium of one load case (what a settled :func:`fpm.simulate` reaches).

    Args:
        problem: from :func:`fpm.load_problem`.
        k: spring stiffness, N/m: one value for every spring, or one per spring family
            (:func:`fpm.model.stiffness.spring_stiffness`; the spec's stiffness_scale applies);
            or the model's :class:`~fpm.model.forces.Stiffness` itself (a field fit's).
        depth: penetration depth in layers; None = the spec's ('full' and 'auto' mean all layers).
        load_case: index into the spec's load cases.
        tolerance: relative force tolerance; None = a tenth of the spec's settle_tolerance.

    Uses this thread's cached :class:`StaticSolver`, so repeated calls start warm.
    """
    if not 0 <= load_case < len(problem.load_cases):
        raise ValueError(f"load_case must be in 0..{len(problem.load_cases) - 1}")
    if not np.all((k.springs if isinstance(k, Stiffness) else np.asarray(k, dtype=float)) > 0):
        raise ValueError("need k > 0")
    if depth is None:
        depth = problem.spec.fpm.layers
    if depth is not None and depth < 0:
        raise ValueError("depth must be >= 0")
    stiffness = model_stiffness(problem, k)
    return static_solver(problem).solve(load_case, stiffness, depth, tolerance=tolerance)
