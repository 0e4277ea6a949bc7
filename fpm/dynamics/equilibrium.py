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
- Newton steps: each tries the exact tangent first (quadratic convergence: a press compresses
  springs, and clamping them cost 2-3 times the iterations); where it is not positive definite
  (CG meets negative curvature, or the step does not descend) the step is redone with the
  factor (1 - L/|r|) clamped at 0, a positive semi-definite tangent whose steps always
  descend; where that is singular (a mechanism), with a small diagonal shift. A backtracking
  (Armijo) line search on E makes every step decrease it (energy changes are computed without
  cancellation: :meth:`~fpm.dynamics.spring_system.SpringSystem.energy_change`);
- linear solves: sparse LU below :data:`AMG_FROM_UNKNOWNS` unknowns; above, conjugate gradients
  preconditioned by a smoothed-aggregation multigrid hierarchy (the FEM's hierarchy, V-cycle
  and CG, from :mod:`fpm.fem.linear_solver`) built on one tangent and kept across Newton steps,
  stiffness changes, load cases and calls for as long as CG converges at the rate it had when
  the hierarchy was new; inexact Newton: CG stops at a residual relative to the current one
  (Eisenstat-Walker, choice 2), or once every node's linear residual is below half the target;
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
import scipy.sparse as sp

from ..fem.linear_solver import (
    NegativeCurvature,
    ReusedHierarchy,
    SingularStiffnessError,
    amg_hierarchy,
    conjugate_gradients,
    factorize,
    rigid_body_modes,
)
from ..model.forces import Stiffness
from ..model.problem import Problem
from ..model.stiffness import model_stiffness
from .predictor import ARMIJO, _galerkin, _largest, _Predictor, _Stats
from .settle import force_tolerance
from .spring_system import Params, SpringSystem, shared_system, spring_lists

AMG_FROM_UNKNOWNS = 300
"""Free unknowns from which the Newton steps use multigrid-preconditioned CG instead of LU: from
about here CG is the faster, and SuperLU's fill-in on the 27-point stencil grows fast with size;
below, LU is as fast and copes with singular tangents (the timings:
docs/notes/2026-11-28-calibration-measured.md, *Thresholds*)."""

MAX_ITERATIONS = 100
"""Newton iterations before a solve gives up (a cold solve of the paper's cube at 1 N needs 4,
of the organ at 20k nodes 3-4; a warm one 0-2)."""

MAX_CG_ITERATIONS = 300
"""CG iterations per Newton step; a step that needs more uses what CG reached (still a descent
direction) and the hierarchy is rebuilt for the next."""

ETA_MAX = 0.1
"""Largest relative CG tolerance of an inexact Newton step (Eisenstat-Walker's eta)."""

NEAR = 1e3
"""Within this factor of the target residual, a Newton step's CG runs to the target (the
quadratic term is negligible there, so one accurate step beats two loose ones)."""

DIVERGED = 10.0
"""A Newton iterate that moves a node this many times the solid's size away has diverged. An
equilibrium further than the size itself is reported as not converged (a dynamic run stops
there as diverged)."""

SHIFT = 1e-8
"""Diagonal shift, relative to the largest diagonal entry, of the last-resort tangent (a
singular one: a mechanism)."""

_MULTIGRID_SETUP = threading.Lock()
"""One multigrid setup at a time in a process: the solvers of chains running at once on threads
would otherwise hold two setups' transients together (a tangent and smoothed aggregation's
intermediates, about 0.5 GB each on the 93,705-node organ), the peak of the calibration."""

MAX_SYSTEMS = 6
"""Spring systems (distinct perturbed lists) a solver keeps, with their multigrid hierarchies
and warm starts: at 20k nodes one full-depth system with its hierarchy takes ~150 MB."""


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


class StaticSolver:
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
        ``depth`` uses: the depth search's probes, once the depth is chosen (on the 93,705-node
        organ about 0.5 GB that the d prediction would otherwise hold). Solves at ``depth``
        are unchanged to the bit: their systems and warm starts stay."""
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

    def forget(self, *, multigrid: bool = True) -> None:
        """Drop the warm starts (the next solves start from rest) and, unless ``multigrid`` is
        False, the multigrid hierarchies."""
        self._predictors.clear()
        if multigrid:
            self._multigrid.clear()

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

    def _start(
        self,
        predictor: _Predictor,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        applied: float,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Where Newton starts, and dE/du there: rest, or the predictor's guess refined on the
        reduced model."""
        rest = np.zeros((system.n_free, 3))
        if not self.warm or not predictor.snapshots or not len(k.flat):
            return rest, -forces
        scale, spread = predictor.relation(k.flat)
        u = predictor.predict(system.n_free, scale, spread)
        gradient = system.gradient(u, k, forces)
        if not _largest(gradient) < applied:  # worse than rest (the residual at rest: forces)
            return rest, -forces
        stats.start = "predicted"
        if _largest(gradient) > target:
            basis = predictor.basis(scale, spread)
            if basis is not None:
                u, gradient = _galerkin(system, k, forces, u, gradient, basis, target, stats)
        return u, gradient

    def _newton(
        self,
        system: SpringSystem,
        k: Params,
        forces: np.ndarray,
        u: np.ndarray,
        gradient: np.ndarray,
        target: float,
        stats: _Stats,
    ) -> tuple[np.ndarray, float, bool]:
        """Newton with an Armijo line search on E from ``u`` (``gradient`` = dE/du there);
        returns (u, residual, converged)."""
        limit = self.problem.size
        residual = _largest(gradient)
        if residual <= target:
            return u, residual, self._within_size(u, stats)
        eta = ETA_MAX
        previous_norm: float | None = None
        for iteration in range(1, MAX_ITERATIONS + 1):
            stats.iterations = iteration
            norm = float(np.sqrt(np.einsum("ij,ij->", gradient, gradient)))
            if previous_norm is not None:  # Eisenstat-Walker choice 2, safeguarded
                ew = 0.9 * (norm / previous_norm) ** 2
                if 0.9 * eta * eta > 0.1:
                    ew = max(ew, 0.9 * eta * eta)
                eta = min(ETA_MAX, ew)
            if residual <= NEAR * target:  # close: the quadratic term is negligible
                eta = 0.0
            eta = max(eta, 0.5 * target / norm)  # no need to solve past the tolerance
            previous_norm = norm
            step, slope = self._newton_step(system, u, k, gradient, eta, 0.5 * target, stats)
            if step is None:
                stats.message = "the Newton step is not a descent direction (singular tangent?)"
                return u, residual, False
            alpha = 1.0
            for _ in range(40):
                change = system.energy_change(u, alpha * step, k, forces)
                if change <= ARMIJO * alpha * slope:
                    break
                # At round-off level (|slope| tiny against the forces' work) accept a step that
                # lowers the residual instead.
                work = abs(float(np.einsum("ij,ij->", forces, step)))
                if abs(slope) < 1e-11 * work:
                    trial = system.gradient(u + alpha * step, k, forces)
                    if _largest(trial) < residual:
                        break
                # Backtrack: minimiser of the quadratic through E(0), E'(0) and E(alpha).
                quad = -slope * alpha * alpha / (2.0 * (change - slope * alpha))
                alpha = min(max(quad, 0.1 * alpha), 0.5 * alpha) if np.isfinite(quad) else alpha / 2
            else:
                stats.message = f"line search failed at Newton iteration {iteration}"
                return u, residual, False
            u = u + alpha * step
            gradient = system.gradient(u, k, forces)
            residual = _largest(gradient)
            if not np.isfinite(residual) or not np.all(np.isfinite(u)):
                stats.message = "diverged: the state became non-finite"
                return u, float("inf"), False
            if _largest(u) > DIVERGED * limit:
                stats.message = f"diverged: a node moved {DIVERGED:g} x the solid's size away"
                return u, residual, False
            if residual <= target:
                return u, residual, self._within_size(u, stats)
        stats.message = (
            f"no convergence in {MAX_ITERATIONS} Newton iterations "
            f"(residual {residual:.3g} N, target {target:.3g} N)"
        )
        return u, residual, False

    def _within_size(self, u: np.ndarray, stats: _Stats) -> bool:
        """An equilibrium moving a node further than the solid's size is what a dynamic run
        stops at as diverged: not converged."""
        limit = self.problem.size
        if _largest(u) > limit:
            stats.message = (
                f"the equilibrium moves a node further than the solid's size, {limit:g} m"
            )
            return False
        return True

    def _newton_step(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        gradient: np.ndarray,
        eta: float,
        nodal_stop: float,
        stats: _Stats,
    ) -> tuple[np.ndarray | None, float]:
        """The Newton step (M, 3) and its slope gradient . step (< 0), or (None, nan).

        The exact tangent first (quadratic convergence near the solution); where it is not
        positive definite (compressed springs) the clamped one, whose steps always descend;
        where that is singular (a mechanism, e.g. an `axis` lattice at rest) the clamped one
        with a small diagonal shift (Levenberg-Marquardt).
        """
        key = system.free.tobytes()
        buffer = self._buffers.get(key)
        if buffer is None:
            buffer = self._buffers[key] = system.blocks()
        for modified, shift in ((False, 0.0), (True, 0.0), (True, SHIFT)):
            tangent = system.tangent(u, k, modified=modified, shift=shift, out=buffer)
            try:
                x = self._linear_solve(system, u, k, tangent, -gradient.ravel(), eta, nodal_stop)
            except NegativeCurvature as e:
                stats.linear_iterations += e.args[0]
                continue
            except SingularStiffnessError:
                continue
            stats.linear_iterations += x[1]
            step = x[0].reshape(-1, 3)
            slope = float(np.einsum("ij,ij->", gradient, step))
            if slope < 0:
                return step, slope
        return None, float("nan")

    def _linear_solve(
        self,
        system: SpringSystem,
        u: np.ndarray,
        k: Params,
        tangent: sp.bsr_matrix,
        rhs: np.ndarray,
        eta: float,
        nodal_stop: float,
    ) -> tuple[np.ndarray, int]:
        """Solve tangent x = rhs: by LU (exactly) for small systems, else by CG preconditioned
        by the list's multigrid hierarchy (built on the clamped tangent at u when missing or
        stale) to the relative residual eta or the nodal residual ``nodal_stop``, N.
        Returns x and the CG iterations (0 for LU).

        Raises:
            NegativeCurvature: CG found ``tangent`` is not positive definite.
            SingularStiffnessError: LU found it singular.
        """
        if 3 * system.n_free < self.amg_from:
            return _direct_solve(tangent, rhs), 0
        mg = self._hierarchy(system, u, k)
        cg = conjugate_gradients(
            tangent,
            rhs,
            mg.precondition,
            rtol=eta,
            max_iterations=MAX_CG_ITERATIONS,
            nodal_stop=nodal_stop,
        )
        mg.record(cg.iterations, cg.residual, cg.converged)
        return cg.x, cg.iterations

    def multigrid(self, system: SpringSystem) -> ReusedHierarchy | None:
        """The multigrid hierarchy this solver keeps for ``system``'s list (None: none yet)."""
        return self._multigrid.get(system.free.tobytes())

    def _linear_hierarchy(
        self, system: SpringSystem, tangent: sp.sparray | sp.spmatrix
    ) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on ``tangent`` when there is none."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None:
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                blocks = sp.bsr_matrix(tangent, blocksize=(3, 3))
                mg = ReusedHierarchy(amg_hierarchy(blocks, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def _hierarchy(self, system: SpringSystem, u: np.ndarray, k: Params) -> ReusedHierarchy:
        """The list's multigrid hierarchy, built on the clamped tangent at u when missing or
        stale."""
        key = system.free.tobytes()
        mg = self._multigrid.get(key)
        if mg is None or mg.stale:
            self._multigrid.pop(key, None)  # the stale one goes before the new one is built
            nodes = self.problem.nodes[system.free]
            with _MULTIGRID_SETUP:
                reference = system.tangent(u, k, modified=True, shift=SHIFT * 1e-3)
                mg = ReusedHierarchy(amg_hierarchy(reference, rigid_body_modes(nodes)))
            self._multigrid[key] = mg
            self.hierarchies_built += 1
        return mg

    def linear_response(
        self,
        load_case: int,
        stiffness: Stiffness | np.ndarray,
        depth: int | None,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m, of ``load_case``'s list linearised at rest (each spring
        acting along its rest direction) under nodal ``loads`` (N, 3), N; zero off the list.

        Solved to a relative residual of ``rtol`` (LU or multigrid CG as for Newton steps; the
        solve does not count towards the hierarchy's staleness); CG starts from ``guess``
        ((N, 3), m; e.g. a reduced model's answer) when given.

        Raises:
            SingularStiffnessError, NegativeCurvature: the linear lattice is not held (e.g. an
                'axis' lattice at rest is a mechanism).
        """
        system, _ = self.system(load_case, depth)
        k = system.parameters(Stiffness.of(stiffness))
        tangent = system.tangent(np.zeros((system.n_free, 3)), k, modified=True)
        return self.linear_solve(load_case, depth, tangent, loads, guess=guess, rtol=rtol)

    def linear_solve(
        self,
        load_case: int,
        depth: int | None,
        tangent: sp.sparray | sp.spmatrix,
        loads: np.ndarray,
        *,
        guess: np.ndarray | None = None,
        rtol: float = 1e-8,
    ) -> np.ndarray:
        """(N, 3) displacements, m: ``tangent`` (3M, 3M) (a stiffness over the list's free
        nodes, e.g. :meth:`SpringSystem.tangent` at rest) solved for nodal ``loads`` (N, 3), N,
        as :meth:`linear_response` does; zero off the list. ``rtol`` >= 1 asks for one
        multigrid V-cycle only (LU is exact below AMG_FROM_UNKNOWNS)."""
        system, _ = self.system(load_case, depth)
        rhs = np.ascontiguousarray(loads[system.free]).ravel()
        if 3 * system.n_free < self.amg_from:
            x = _direct_solve(tangent, rhs)
        elif rtol >= 1.0:  # one multigrid V-cycle: an approximate answer, for search directions
            x = self._linear_hierarchy(system, tangent).precondition(rhs)
        else:
            start = np.zeros_like(rhs)
            if guess is not None:
                start = np.ascontiguousarray(guess[system.free]).ravel()
            left = rhs - tangent @ start
            size, remaining = float(np.linalg.norm(rhs)), float(np.linalg.norm(left))
            x = start
            if remaining > rtol * size:
                mg = self._linear_hierarchy(system, tangent)
                cg = conjugate_gradients(
                    tangent, left, mg.precondition, rtol=rtol * size / remaining,
                    max_iterations=10 * MAX_CG_ITERATIONS,
                )  # fmt: skip
                x = start + cg.x
        out = np.zeros_like(self.problem.nodes)
        out[system.free] = x.reshape(-1, 3)
        return out


def _direct_solve(tangent: sp.bsr_matrix, rhs: np.ndarray) -> np.ndarray:
    """Sparse LU solve (:func:`fpm.fem.linear_solver.factorize`).

    Raises:
        SingularStiffnessError: the tangent is singular, or the solve is not finite.
    """
    x = factorize(tangent.tocsc(), "direct", np.zeros((0, 6)))(rhs)
    if not np.all(np.isfinite(x)):
        raise SingularStiffnessError("the LU solve is not finite")
    return np.asarray(x)


_SOLVERS = threading.Lock()


def static_solver(problem: Problem) -> StaticSolver:
    """This thread's :class:`StaticSolver` of ``problem``, built on first use and kept on the
    problem (``problem.cache["static_solvers"]``, one per thread)."""
    local = problem.cache.get("static_solvers")
    if local is None:
        with _SOLVERS:
            local = problem.cache.setdefault("static_solvers", threading.local())
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
