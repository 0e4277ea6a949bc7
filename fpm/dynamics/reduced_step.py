"""The FPM step of one load case near its equilibrium, reduced to the lattice's slowest modes:
one mode alone, and the modes together, each predicting how many steps a run takes at a nodal
damping d (docs/physics.md, *Calibration*, damping: *the prediction*). The modes themselves:
:mod:`fpm.dynamics.eigen`; the d they predict fastest: :mod:`fpm.dynamics.modes`.

**The step near equilibrium.** A run of one load case moves the M nodes of its perturbed list;
near the static equilibrium x* its error e = x - x*, (3M,) m, evolves linearly. With K the
tangent at rest (3M, 3M), N/m (springs and cells; fixed nodes and nodes off the list held),
M the lumped masses (kg, one per unknown) and the step of :mod:`fpm.dynamics.voigt`
(``(m + dt d) v+ = m v + dt F``, ``x+ = x + dt v+``, node by node), eliminating v:

    (M + dt d I + dt^2 L) e+ = (2 M + dt d I - dt^2 (K - L)) e - M e-                  (1)

e+ and e- the errors one step on and one step back; L the strictly lower 3x3-block part of the
springs' tangent K_s in list order (node i sees the new positions of the nodes visited before
it; springs to held nodes sit on the diagonal); the cells' part of K acts at the positions at
the step's start, all at once (:mod:`fpm.dynamics.stability`, step 4). A run starts at rest:
e = e- = -u*, u* (3M,) the static displacement.

**2. One mode alone** (:func:`mode_damping`, the diagonal of (1) on phi). With h = dt w,
c = dt d phi^T phi, g = dt^2 phi^T D phi (D: K_s's 3x3 diagonal blocks) and
s^2 = dt^2 phi^T K_s phi, and since L + L^T = K_s - D, phi^T L phi = (phi^T K_s phi - phi^T D
phi) / 2, the error along phi, e_n = z^n, obeys

    (z - 1)^2 + z (z - 1) C + z h^2 = 0,       C = c + (s^2 - g) / 2,                  (2)

i.e. z^2 (1 + C) - z (2 + C - h^2) + 1 = 0: two roots of modulus 1 / sqrt(1 + C) while they
are complex, one of them slower once they are real. The mode settles fastest where they meet,
C = 2 h + h^2, at

    d* = (2 h + h^2 + (g - s^2) / 2) / (dt phi^T phi),   the roots then 1 / (1 + h).      (3)

All nodes at once (L = 0) this is d* = (2 h + h^2) / (dt phi^T phi), the critical damping
2 w / (phi^T phi) plus dt w^2 / (phi^T phi). The node-by-node order takes (g - s^2) / 2 off the
damping: for a slow mode g >> s^2 (its springs barely stretch, but every node feels its
neighbours' pull), so the fastest d sits 2-4 times above the lowest mode's critical
damping.

**3. The reduced step** (:class:`StepModel`): (1) projected on the modes, e = Phi q, with
P = Phi^T Phi (1/kg), Kr = Phi^T K Phi = diag(w^2) and Lr = Phi^T L Phi (1/s^2),

    (I + dt d P + dt^2 Lr) q+ = (2 I + dt d P - dt^2 (Kr - Lr)) q - q-,   q = q- = -Phi^T M u*,

a 2k x 2k iteration T(d). Unlike (2) it keeps the modes' couplings: Lr is not symmetric, so the
step feeds motion into modes the load does not excite (on the paper's cube the symmetric pull
excites one of the lowest four modes, yet the two lowest, sideways, set the fastest d). The
residual of the settle test (largest |F_i + F_s| of a sweep, N) is ~ |(K Phi q)_i|, followed at
the nodes where the modes' residuals peak and at the loaded nodes; the predicted steps are the
first step it falls below the settle force. On the target criterion of
:mod:`fpm.dynamics.settle` the test reads the reach ``sqrt(q^T P q + |dq/dt|^2 / lambda)``
(times the slowest mode's sum of nodal lengths over its 2-norm: the run sums nodal lengths),
which the slowest modes hold: there the reduced step sees what the run reads. The fastest d
(:func:`fpm.dynamics.modes.fastest_predicted`) minimises the predicted steps summed over the
load cases.

tests/core/test_spectrum.py checks the parts on lattices small enough for dense eigensolves and on a
1-D chain whose modes are known in closed form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..model.forces import Stiffness
from .eigen import Modes, _gram, _gram_into
from .settle import mode_stiffness, nodal_size
from .spring_system import Params, SpringSystem

PEAK_NODES = 8
"""Per mode, the nodes with the largest residual shape |(K phi)_i| whose residual the
prediction follows (with the loaded nodes)."""
CHECK_EVERY = 4
"""The reduced step's residual is checked every this many steps (the predicted steps are a
multiple of it)."""
NEVER = math.inf
"""Predicted steps of a run that does not settle."""


@dataclass
class ModeDamping:
    """One mode alone in the node-by-node step (the module docstring's (2) and (3)).

    Attributes:
        h: dt w, the mode's phase per step.
        g: dt^2 phi^T D phi (D the springs' diagonal blocks).
        s2: dt^2 phi^T K_s phi (K_s the springs' tangent).
        mobility: phi^T phi, 1/kg (with phi M-normalised).
        dt: the time step, s.
    """

    h: float
    g: float
    s2: float
    mobility: float
    dt: float

    @property
    def fastest(self) -> float:
        """d*, N s/m: where the mode's two roots meet (3)."""
        c = 2 * self.h + self.h**2 + (self.g - self.s2) / 2
        return c / (self.dt * self.mobility)

    def radius(self, d: float) -> float:
        """The mode's decay per step at d: the larger modulus of the roots of (2)."""
        big_c = self.dt * d * self.mobility + (self.s2 - self.g) / 2
        return float(np.abs(np.roots([1 + big_c, -(2 + big_c - self.h**2), 1.0])).max())


def mode_damping(
    w2: float, shape: np.ndarray, spring_tangent: sp.spmatrix | sp.sparray, dt: float
) -> ModeDamping:
    """:class:`ModeDamping` of one M-normalised mode ``shape`` (3M,) with squared frequency
    ``w2`` (1/s^2) under the springs' tangent ``spring_tangent`` (3M, 3M) N/m at ``dt`` s."""
    blocks = sp.bsr_matrix(spring_tangent, blocksize=(3, 3))
    coo = sp.coo_matrix(blocks)
    same = (coo.row // 3) == (coo.col // 3)
    diagonal = sp.csr_matrix((coo.data[same], (coo.row[same], coo.col[same])), shape=coo.shape)
    return ModeDamping(
        h=dt * math.sqrt(max(w2, 0.0)),
        g=dt**2 * float(shape @ (diagonal @ shape)),
        s2=dt**2 * float(shape @ (spring_tangent @ shape)),
        mobility=float(shape @ shape),
        dt=dt,
    )


def lower_projection(
    system: SpringSystem, k: Params, rank: np.ndarray, shapes: np.ndarray
) -> np.ndarray:
    """Phi^T L Phi (k, k), N/m kg^-1: L the strictly lower block part, in list order, of the
    springs' tangent at rest (each spring k n n^T, n its unit vector at rest) over ``system``'s
    free nodes; ``rank`` (M,) each free node's place in the list, ``shapes`` (3M, k).

    A spring between free nodes a and b adds -k n n^T at (later, earlier) to L, so
    Phi^T L Phi = -sum_s k_s (Phi_later^T n)(n^T Phi_earlier), summed in pieces."""
    ends = system.ends
    both = np.flatnonzero((ends[:, 0] >= 0) & (ends[:, 1] >= 0))
    phi = shapes.reshape(-1, 3, shapes.shape[1])
    out = np.zeros((shapes.shape[1], shapes.shape[1]))
    for start in range(0, len(both), 200_000):
        # summed over 200,000 springs at a time, each sum taken 25,000 springs at a time
        chunk = np.zeros_like(out)
        for piece in range(start, min(start + 200_000, len(both)), 25_000):
            s = both[piece : min(piece + 25_000, start + 200_000)]
            a, b = ends[s, 0], ends[s, 1]
            later = np.where(rank[a] > rank[b], a, b)
            earlier = np.where(rank[a] > rank[b], b, a)
            n = system.rest_vector[s] / np.linalg.norm(system.rest_vector[s], axis=1)[:, None]
            left = np.einsum("sd,sdk->sk", n, phi[later]) * k.springs[s][:, None]
            right = np.einsum("sd,sdk->sk", n, phi[earlier])
            _gram_into(chunk, left, right)
        out -= chunk
    return out


@dataclass
class StepModel:
    """The FPM step of one load case reduced to the lowest modes (the module docstring's 3).

    Attributes:
        dt: time step, s.
        mobility: (k, k) P = Phi^T Phi, 1/kg.
        stiffness: (k, k) Kr = Phi^T K Phi, 1/s^2.
        lower: (k, k) Lr = Phi^T L Phi, 1/s^2.
        start: (k,) q at rest, -Phi^T M u* (kg^1/2 m).
        residual: (c, 3, k) rows of K Phi at the followed nodes, N per unit q.
        settle_force: the settle test's force, N (0: never settles).
        mode_stiffness: the list's mode stiffness, N/m (:func:`fpm.dynamics.settle.mode_stiffness`).
        residual_gram: (k, k) (K Phi)^T (K Phi), N^2 per unit q^2: the settle test reads the
            2-norm of the residual over the list (the distance criterion); None: its largest
            nodal value at the followed nodes (the force criterion).
        slowness: 1 / lambda, m/N, > 0: the settle test reads the state's reach from the static
            equilibrium (the target criterion of :mod:`fpm.dynamics.settle`), m, and
            ``settle_force`` is its reach: read as ``spread * sqrt(|Phi q|^2 + |dq/dt|^2
            slowness)``, with ``spread`` the slowest mode's sum of nodal lengths over its
            2-norm (the reach is a sum of nodal lengths; late in a run the slowest mode holds
            the error).
    """

    dt: float
    mobility: np.ndarray
    stiffness: np.ndarray
    lower: np.ndarray
    start: np.ndarray
    residual: np.ndarray
    settle_force: float
    mode_stiffness: float = 0.0
    residual_gram: np.ndarray | None = None
    slowness: float = 0.0
    spread: float = 1.0

    def iteration(self, d: float) -> np.ndarray:
        """(2k, 2k) T(d): (q+, q) = T (q, q-)."""
        k = len(self.start)
        eye = np.eye(k)
        a = eye + self.dt * d * self.mobility + self.dt**2 * self.lower
        b = 2 * eye + self.dt * d * self.mobility - self.dt**2 * (self.stiffness - self.lower)
        inverse = np.linalg.inv(a)
        return np.block([[inverse @ b, -inverse], [eye, np.zeros((k, k))]])

    def radius(self, d: float) -> float:
        """Spectral radius of T(d): the slowest decay per step (>= 1: grows or never settles)."""
        return float(np.abs(np.linalg.eigvals(self.iteration(d))).max())

    def steps(self, d: float, cap: int) -> float:
        """Predicted steps to settle at d, or :data:`NEVER` when the reduced step does not
        decay or settle within ``cap``. The residual is checked every :data:`CHECK_EVERY`
        steps; between the last check above the settle force and the first below, the
        crossing is interpolated on its logarithm (so the steps vary continuously with d)."""
        if self.settle_force <= 0:
            return NEVER
        t = self.iteration(d)
        if np.abs(np.linalg.eigvals(t)).max() >= 1.0:
            return NEVER
        jump = np.linalg.matrix_power(t, CHECK_EVERY)
        block = 64
        # states after CHECK_EVERY * (1..block) steps from any state: one product per block
        powers = [jump]
        for _ in range(block - 1):
            powers.append(jump @ powers[-1])
        stacked = np.stack(powers)  # (block, 2k, 2k)
        state = np.concatenate([self.start, self.start])
        last = float(self._level(state[None, :])[0])
        if last < self.settle_force:
            return 0.0
        taken = 0
        while taken < cap:
            states = stacked @ state  # (block, 2k)
            levels = self._level(states)
            below = np.flatnonzero(levels < self.settle_force)
            if len(below):
                i = int(below[0])
                above = last if i == 0 else float(levels[i - 1])
                fall = math.log(above / max(float(levels[i]), 1e-300))
                part = math.log(above / self.settle_force) / fall if fall > 0 else 1.0
                return float(taken + CHECK_EVERY * (i + min(max(part, 0.0), 1.0)))
            state = states[-1]
            last = float(levels[-1])
            taken += CHECK_EVERY * block
        return NEVER

    def _level(self, states: np.ndarray) -> np.ndarray:
        """(n,) what the settle test reads of the reduced states (n, 2k) (q, q-): the reach
        from the static equilibrium, m (``slowness`` > 0), or the residual's 2-norm, or its
        largest nodal value (``residual_gram`` None), N."""
        k = len(self.start)
        q = states[:, :k]
        if self.slowness > 0:
            rate = (q - states[:, k:]) / self.dt
            reach2 = np.einsum("nk,kl,nl->n", q, self.mobility, q)
            kinetic = self.slowness * (rate * rate).sum(axis=1)
            return self.spread * np.sqrt(np.maximum(reach2 + kinetic, 0.0))
        if self.residual_gram is not None:
            return np.sqrt(np.maximum(np.einsum("nk,kl,nl->n", q, self.residual_gram, q), 0.0))
        rows = self.residual.reshape(-1, self.residual.shape[2])  # (3c, k)
        r = (q @ rows.T).reshape(len(q), -1, 3)
        return np.sqrt((r * r).sum(axis=2)).max(axis=1)


def step_model(
    system: SpringSystem,
    stiffness: Stiffness,
    order: np.ndarray,
    modes: Modes,
    masses: np.ndarray,
    dt: float,
    loads: np.ndarray,
    settle_force: float,
    displacement: np.ndarray | None = None,
    norm: bool = False,
) -> StepModel:
    """The reduced step of one load case.

    Args:
        system: the list's spring system (its free nodes are ``modes.free``).
        stiffness: the model's stiffness.
        order: (M,) the list's nodes in visiting order.
        modes: the list's lowest modes.
        masses: (N,) lumped masses, kg.
        dt: time step, s.
        loads: (N, 3) constant nodal forces, N (gravity included).
        settle_force: the settle test's force, N.
        displacement: (N, 3) the static equilibrium u*, m; None: the modes' linear response
            to ``loads`` (q = -Phi^T f / w^2).
        norm: the settle test reads the residual's 2-norm (the distance criterion), not its
            largest nodal value; with ``displacement`` given, the state's reach from it (the
            target criterion, ``settle_force`` then its reach, m).
    """
    k = system.parameters(stiffness)
    rank = np.empty(system.n_free, dtype=np.int64)
    rank[np.searchsorted(system.free, order)] = np.arange(len(order))
    phi = modes.shapes
    m = np.repeat(masses[system.free], 3)
    f = loads[system.free].ravel()
    if displacement is None:
        start = -np.einsum("ik,i->k", phi, f) / modes.w2
    else:
        start = -np.einsum("ik,i->k", phi, m * displacement[system.free].ravel())
    kphi = modes.kshapes.reshape(-1, 3, phi.shape[1])
    size = np.sqrt(np.einsum("ndk,ndk->nk", kphi, kphi))
    peaks = np.argsort(-size, axis=0)[:PEAK_NODES].ravel()
    loaded = np.flatnonzero(np.abs(loads[system.free]).sum(axis=1) > 0)
    followed = np.unique(np.concatenate([peaks, loaded]))
    lowest = mode_stiffness(modes.w2, phi)
    slowest = phi[:, int(np.argmin(modes.w2))]
    return StepModel(
        dt=float(dt),
        mobility=_gram(phi, phi),
        stiffness=_gram(phi, np.ascontiguousarray(modes.kshapes)),
        lower=lower_projection(system, k, rank, phi),
        start=start,
        residual=kphi[followed],
        settle_force=float(settle_force),
        mode_stiffness=lowest,
        residual_gram=_gram(modes.kshapes, modes.kshapes) if norm else None,
        slowness=1.0 / lowest if norm and displacement is not None else 0.0,
        spread=nodal_size(slowest.reshape(-1, 3)) / float(np.linalg.norm(slowest)),
    )
