"""The large-deformation FEM reference: compressible neo-Hookean hexahedra under dead loads.

Total Lagrangian (:mod:`fpm.fem.neo_hookean`: the strain energy, its stress and tangent, on the
linear FEM's hexahedra and 2x2x2 Gauss points). Equilibrium: the residual
``R(u) = f_int(u) - s f`` vanishes on the free unknowns, ``f`` the load case's nodal forces
(dead loads: fixed in size and direction), ``s`` the load factor. Each load case is solved on
its own, from rest:

- *load steps*: ``s`` goes from 0 to 1 in ``load_steps`` equal steps (default 1). A step whose
  Newton iterations fail is halved and retried from the last converged state, at most
  :data:`MAX_STEP_HALVINGS` times; after a success the step grows back (doubling) to the planned
  size. Each step starts from the previous solution extrapolated linearly along the load factor
  (unless that inverts an element);
- *Newton*: the tangent ``K = dR/du`` (assembled into the linear FEM's block pattern), the
  step ``K du = -R`` solved by the project's solver stack (:mod:`fpm.fem.linear_solver`: sparse LU
  below :data:`fpm.fem.linear_solver.AMG_FROM_UNKNOWNS` unknowns, else conjugate gradients with a
  rigid-body-mode smoothed-aggregation multigrid, the hierarchy kept while CG stays fast;
  inexact: CG stops at a tolerance tied to the current residual), then a backtracking line
  search on the residual norm that also rejects any trial state with det F <= 0 at a Gauss
  point. Converged when ``||R|| <= NEWTON_TOLERANCE ||f||`` (free unknowns);
- *failure*: a load step that still fails at 1 / 2^MAX_STEP_HALVINGS of its planned size
  raises :class:`NewtonError` naming the load case, the load step and the reason (an inverted
  hexahedron along the whole Newton step, the iteration cap, no descent, a tangent that is not
  positive definite, an iterate moving a node more than :data:`DIVERGED` times the solid's
  size, which is what a units slip looks like). Every loop is capped, so a solve never hangs.

Small loads reproduce the linear FEM (the tangent at rest is the linear stiffness).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..model.spec import UNITS_HINT
from .assembly import keep_nodes, unique_inverse
from .linear_solver import (
    COMPILED_SMOOTHER_FROM,
    NegativeCurvature,
    ReusedHierarchy,
    SingularStiffnessError,
    amg_hierarchy,
    conjugate_gradients,
    factorize,
    rigid_body_modes,
)
from .neo_hookean import (
    MeanDilatationNeoHookean,
    NeoHookeanLaw,
    ReferenceGradients,
    kinematics,
    reference_gradients,
)
from .solution import FemError

NEWTON_TOLERANCE = 1e-10
"""Converged at ||R|| <= this times ||f|| over the free unknowns (R the unbalanced force)."""

MAX_NEWTON_ITERATIONS = 25
"""Newton iterations per load step before the step counts as failed (then it is halved)."""

MAX_STEP_HALVINGS = 6
"""A failing load step is halved at most this many times (down to 1/64 of its planned size)
before the solve gives up with :class:`NewtonError`."""

LINE_SEARCH_HALVINGS = 12
"""Backtracking halves the Newton step at most this many times (down to 1/4096)."""

ARMIJO = 1e-4
"""Sufficient decrease of the line search: ||R(u + a du)|| <= (1 - ARMIJO a) ||R(u)||."""

DIVERGED = 10.0
"""A Newton iterate that moves a node more than this times the solid's size (bounding-box
diagonal) fails the load step (as in :mod:`fpm.dynamics.equilibrium`): no equilibrium nearby."""

ETA_MAX = 1e-2
"""Loosest relative CG tolerance of an inexact Newton step (multigrid path)."""

MAX_CG_ITERATIONS = 500
"""CG iterations per Newton step; a solve that needs more marks the hierarchy stale."""

CHUNK = 1024
"""Hexahedra whose element matrices are formed at once (bounds the memory of an assembly)."""


SELECTIVE_HINT = (
    "; the selective (mean-dilatation) hexahedra give way sooner under a load on few nodes: "
    "reference.integration 'full' follows such a load further, but locks as nu nears 0.5"
)
"""Added to a failure of the selective neo-Hookean solid (docs/physics.md, *Large deformation
reference*, its limit)."""


class NewtonError(FemError):
    """The neo-Hookean equilibrium was not found: the message names the load case and step."""


class _StepFailed(Exception):
    """One load step's Newton iterations failed; ``args[0]`` says why."""


@dataclass
class LoadPath:
    """How one load case was solved.

    Attributes:
        load_factors: (S,) load factor at the end of each converged load step (the last is 1).
        newton_iterations: (S,) Newton iterations of each converged load step.
        residual_history: per converged step, ||R|| / ||f|| before each Newton iteration and
            after the last (so ``newton_iterations[s] + 1`` values).
        residual: final ||R|| / ||f|| over the free unknowns.
    """

    load_factors: list[float] = field(default_factory=list)
    newton_iterations: list[int] = field(default_factory=list)
    residual_history: list[list[float]] = field(default_factory=list)
    residual: float = 0.0

    @property
    def load_steps(self) -> int:
        """Converged load steps."""
        return len(self.load_factors)


class NeoHookeanSolid:
    """The discretised solid: residual, tangent and the linear solves of Newton's method.

    Args:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices, :mod:`fpm.model.hexahedron` order, det J > 0.
        law: the material and its integration (:func:`fpm.fem.neo_hookean.neo_hookean_law`).
        free: (N, 3) or (3N,) bool, the unknowns that may move (the others stay at zero).
        method: ``"direct"`` (sparse LU) or ``"amg"`` (multigrid-preconditioned CG).
    """

    def __init__(
        self,
        nodes: np.ndarray,
        hexahedra: np.ndarray,
        law: NeoHookeanLaw,
        free: np.ndarray,
        method: str,
    ):
        if method not in ("direct", "amg"):
            raise ValueError(f"unknown method {method!r} (use 'direct' or 'amg')")
        self.nodes = nodes
        self.law = law
        self.free = np.asarray(free, dtype=bool).reshape(-1)
        self.method = method
        self.size = float(np.linalg.norm(np.ptp(nodes, axis=0)))
        self.ref: ReferenceGradients = reference_gradients(nodes, hexahedra)
        self._pattern(hexahedra.astype(np.int64))
        self._hierarchy: ReusedHierarchy | None = None

    # --- assembly ---------------------------------------------------------------------------

    def _pattern(self, hexahedra: np.ndarray) -> None:
        """The tangent's block pattern (that of the linear K, cut to the free nodes when whole
        nodes are free) and, per run of :data:`CHUNK` hexahedra, a sparse matrix summing their
        element blocks into the pattern's blocks."""
        n = len(self.nodes)
        keys = (np.repeat(hexahedra, 8, axis=1) * n + np.tile(hexahedra, (1, 8))).ravel()
        pairs, slot = unique_inverse(keys)
        indptr = np.searchsorted(pairs // n, np.arange(n + 1))
        per_node = self.free.reshape(-1, 3)
        self.whole_nodes = bool(np.array_equal(per_node.all(axis=1), per_node.any(axis=1)))
        if self.whole_nodes:  # keep 3x3 blocks: sum straight into the free nodes' blocks
            ids = np.repeat(np.arange(1, len(pairs) + 1, dtype=float), 9).reshape(-1, 3, 3)
            full = sp.bsr_matrix((ids, pairs % n, indptr), shape=(3 * n, 3 * n))
            reduced = keep_nodes(full, per_node[:, 0])
            kept = np.zeros(len(pairs) + 1, dtype=np.int64)  # pattern block -> reduced + 1
            kept[reduced.data[:, 0, 0].astype(np.int64)] = np.arange(1, len(reduced.data) + 1)
            slot = kept[slot + 1] - 1  # -1: a block of a fixed node, dropped
            self._indices, self._indptr = reduced.indices, reduced.indptr
            self._size, blocks = reduced.shape[0], len(reduced.data)
        else:  # per-unknown supports (rollers): assemble all, then slice
            self._indices, self._indptr = pairs % n, indptr
            self._size, blocks = 3 * n, len(pairs)
        self._runs = []
        for start in range(0, len(hexahedra), CHUNK):
            part = slice(start, min(start + CHUNK, len(hexahedra)))
            rows = slot[64 * part.start : 64 * part.stop]
            used = np.flatnonzero(rows >= 0)
            summing = sp.csr_matrix(
                (np.ones(len(used)), (rows[used], used)), shape=(blocks, len(rows))
            )
            self._runs.append((start, self.ref.part(part), summing))

    def tangent(self, u: np.ndarray) -> sp.bsr_matrix | sp.csr_matrix:
        """dR/du over the free unknowns at nodal displacements ``u`` (N, 3), N/m."""
        data = np.zeros((len(self._indices), 9))
        for _, ref, summing in self._runs:
            blocks = self.law.tangents(ref, kinematics(ref, u))
            data += summing @ blocks.reshape(-1, 9)
        k = sp.bsr_matrix(
            (data.reshape(-1, 3, 3), self._indices, self._indptr), shape=(self._size,) * 2
        )
        if self.whole_nodes:
            return k
        return k.tocsr()[self.free][:, self.free]

    def residual(
        self, u: np.ndarray, load: np.ndarray
    ) -> tuple[np.ndarray, tuple[int, float] | None]:
        """R = f_int(u) - load over the free unknowns (M,), N, and a hexahedron and its
        smallest det F when some Gauss point has det F <= 0 (else None; R is then not valid).

        ``u``: (N, 3) displacements, m; ``load``: (N, 3) nodal forces, N.
        """
        forces = -load
        for start, ref, _ in self._runs:
            kin = kinematics(ref, u)
            smallest = kin.det.min(axis=1)
            worst = int(np.argmin(smallest))
            if not smallest[worst] > 0:
                return np.empty(0), (start + worst, float(smallest[worst]))
            forces = forces + self.law.forces(ref, kin, len(u))
        return forces.reshape(-1)[self.free], None

    # --- linear solves ----------------------------------------------------------------------

    def solve(
        self, k: sp.bsr_matrix | sp.csr_matrix, rhs: np.ndarray, rtol: float, u: np.ndarray
    ) -> np.ndarray:
        """x with k x = rhs: by LU (exactly) or by multigrid CG to ``rtol``; ``u`` (N, 3), m,
        the current displacements (the multigrid's rigid-body modes rotate about x = X + u).

        Raises:
            _StepFailed: the tangent is singular or not positive definite.
        """
        if self.method == "direct":
            try:
                return factorize(k, "direct", np.empty((0, 6)))(rhs)
            except SingularStiffnessError:
                raise _StepFailed("the tangent stiffness is singular") from None
        for attempt in range(2):
            if self._hierarchy is None or self._hierarchy.stale:
                self._hierarchy = None  # free the old one first
                modes = rigid_body_modes(self.nodes + u)[self.free]
                compiled = k.shape[0] >= COMPILED_SMOOTHER_FROM  # as the linear FEM
                self._hierarchy = ReusedHierarchy(amg_hierarchy(k, modes, compiled=compiled))
            mg = self._hierarchy
            try:
                cg = conjugate_gradients(
                    k, rhs, mg.precondition, rtol=rtol, max_iterations=MAX_CG_ITERATIONS
                )
            except NegativeCurvature:
                mg.stale = True
                if attempt:
                    raise _StepFailed(
                        "the tangent stiffness is not positive definite (the solid buckles or "
                        "a hexahedron is close to inverting)"
                    ) from None
                continue
            mg.record(cg.iterations, cg.residual, cg.converged)
            return cg.x
        raise AssertionError("unreachable")


def newton(
    solid: NeoHookeanSolid, u0: np.ndarray, load: np.ndarray, scale: float
) -> tuple[np.ndarray, list[float]]:
    """Equilibrium under nodal ``load`` (N, 3), N, from ``u0`` (N, 3), m.

    Returns the displacements (N, 3), m, and the relative residual ||R|| / ``scale`` before
    each iteration and after the last.

    Raises:
        _StepFailed: the iteration cap, an inverted hexahedron along the whole step, no
            decrease of the residual, or a tangent the linear solver refuses.
    """
    u = u0.copy()
    r, inverted = solid.residual(u, load)
    if inverted is not None:
        raise _StepFailed(_inverted(inverted, "at the start of the step"))
    history = [float(np.linalg.norm(r)) / scale]
    for _ in range(MAX_NEWTON_ITERATIONS):
        if history[-1] <= NEWTON_TOLERANCE:
            return u, history
        rel = history[-1]
        rtol = min(ETA_MAX, max(rel, 0.1 * NEWTON_TOLERANCE / rel))
        flat = np.zeros(u.size)
        flat[solid.free] = solid.solve(solid.tangent(u), -r, rtol, u)
        step = flat.reshape(u.shape)
        norm = float(np.linalg.norm(r))
        alpha = 1.0
        for _ in range(LINE_SEARCH_HALVINGS + 1):
            trial = u + alpha * step
            r_trial, inverted = solid.residual(trial, load)
            if inverted is None and np.linalg.norm(r_trial) <= (1 - ARMIJO * alpha) * norm:
                break
            alpha /= 2
        else:
            if inverted is not None:
                raise _StepFailed(_inverted(inverted, "however short the Newton step"))
            raise _StepFailed(
                f"the residual does not decrease along the Newton step (relative residual "
                f"{history[-1]:.2g})"
            )
        u, r = trial, r_trial
        history.append(float(np.linalg.norm(r)) / scale)
        moved = np.linalg.norm(u, axis=1)
        if moved.max() > DIVERGED * solid.size:
            node = int(np.argmax(moved))
            raise _StepFailed(
                f"a Newton iterate moves node {node} by {moved[node]:.3g} m, more than "
                f"{DIVERGED:g} times the solid's size ({solid.size:.3g} m)"
            )
    if history[-1] <= NEWTON_TOLERANCE:
        return u, history
    raise _StepFailed(
        f"relative residual {history[-1]:.2g} after {MAX_NEWTON_ITERATIONS} Newton iterations "
        f"(tolerance {NEWTON_TOLERANCE:g})"
    )


def _inverted(where: tuple[int, float], when: str) -> str:
    element, det = where
    return f"hexahedron {element} inverts (det F = {det:.3g} <= 0 at a Gauss point) {when}"


def load_path(
    solid: NeoHookeanSolid, forces: np.ndarray, load_steps: int = 1, name: str = ""
) -> tuple[np.ndarray, LoadPath]:
    """Displacements (N, 3), m, of one load case's nodal ``forces`` (N, 3), N, applied in
    ``load_steps`` equal load steps from rest (halved where Newton fails: module docstring).

    Raises:
        NewtonError: a load step failed even at 1 / 2^MAX_STEP_HALVINGS of its planned size.
    """
    if load_steps < 1:
        raise ValueError("load_steps must be >= 1")
    u = np.zeros_like(forces, dtype=float)
    path = LoadPath()
    scale = float(np.linalg.norm(forces.reshape(-1)[solid.free]))
    if scale == 0.0:
        path.residual_history.append([0.0])
        path.load_factors.append(1.0)
        path.newton_iterations.append(0)
        return u, path
    planned = 1.0 / load_steps
    step, factor = planned, 0.0
    previous: tuple[float, np.ndarray] | None = None  # (factor, u) of the step before
    smallest = planned / 2**MAX_STEP_HALVINGS
    while factor < 1.0:
        end = 1.0 if factor + step > 1.0 - 1e-12 else factor + step
        start = u
        if previous is not None:  # extrapolate along the load factor
            guess = u + (end - factor) / (factor - previous[0]) * (u - previous[1])
            if solid.residual(guess, end * forces)[1] is None:
                start = guess
        try:
            u_next, history = newton(solid, start, end * forces, scale)
        except _StepFailed as failure:
            if step <= smallest * (1 + 1e-9):
                raise NewtonError(
                    f"neo-Hookean FEM, load case '{name}': Newton did not converge in load step "
                    f"{path.load_steps + 1} (load factor {factor:.4g} -> {end:.4g} of the load, "
                    f"the step already halved {MAX_STEP_HALVINGS} times): {failure.args[0]}; a "
                    "load this large for the mesh cannot be followed: lower the forces, spread "
                    f"them over more nodes, or check the units ({UNITS_HINT})"
                    + (SELECTIVE_HINT if isinstance(solid.law, MeanDilatationNeoHookean) else "")
                ) from None
            step /= 2
            continue
        previous = (factor, u)
        u, factor = u_next, end
        path.load_factors.append(end)
        path.newton_iterations.append(len(history) - 1)
        path.residual_history.append(history)
        path.residual = history[-1]
        step = min(planned, 2 * step)
    return u, path


def solve_hyperelastic(
    nodes: np.ndarray,
    hexahedra: np.ndarray,
    law: NeoHookeanLaw,
    forces: np.ndarray,
    free: np.ndarray,
    method: str,
    names: list[str] | None = None,
    load_steps: int = 1,
) -> tuple[np.ndarray, list[LoadPath]]:
    """Neo-Hookean displacements of every load case.

    Args:
        nodes: (N, 3) rest positions, m.
        hexahedra: (H, 8) node indices, :mod:`fpm.model.hexahedron` order, det J > 0.
        law: the material and its integration (:func:`fpm.fem.neo_hookean.neo_hookean_law`).
        forces: (L, N, 3) nodal dead loads, N.
        free: (N, 3) or (3N,) bool, unknowns that may move (the rest stay at zero).
        method: ``"direct"`` or ``"amg"`` for the Newton steps' linear solves.
        names: (L,) load case names for error messages.
        load_steps: planned load steps per load case.

    Returns:
        (L, N, 3) displacements, m, and one :class:`LoadPath` per load case.

    Raises:
        NewtonError: a load case whose equilibrium was not found (names it and the load step).
    """
    solid = NeoHookeanSolid(nodes, hexahedra, law, free, method)
    names = names or [str(j) for j in range(len(forces))]
    out, paths = np.zeros_like(forces, dtype=float), []
    for j, f in enumerate(forces):
        out[j], path = load_path(solid, f, load_steps, names[j])
        paths.append(path)
    return out, paths
