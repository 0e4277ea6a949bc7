"""The lattice's slowest modes, and what they predict for the FPM step: how many steps a run of
a load case takes at a nodal damping d, and the d that settles fastest (docs/physics.md,
*Calibration*, damping: *the prediction*).

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

**1. The slowest modes** (:func:`fpm.dynamics.eigen.lowest_modes`): ``K phi = w^2 M phi``,
the k lowest, as Phi (3M, k) M-orthonormal (Phi^T M Phi = I; kg^-1/2) and w^2 (k,) 1/s^2.

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
(:func:`fastest_predicted`) minimises the predicted steps summed over the load cases.

How close the prediction comes to the dynamic kernel's runs:
docs/explanation/physics/damping-prediction.md. tests/test_spectrum.py checks the parts on
lattices small enough for dense eigensolves and on a 1-D chain whose modes are known in closed
form.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..fem.linear_solver import SingularStiffnessError
from ..model.forces import Stiffness
from ..model.problem import Problem
from .eigen import DENSE_UP_TO, MODES, Modes, _gram, _gram_into, lowest_modes, single_threaded_blas
from .equilibrium import StaticSolver
from .settle import by_distance, force_tolerance, mode_stiffness, nodal_size, nominal_distance
from .spring_system import Params, SpringSystem

PEAK_NODES = 8
"""Per mode, the nodes with the largest residual shape |(K phi)_i| whose residual the
prediction follows (with the loaded nodes)."""
CHECK_EVERY = 4
"""The reduced step's residual is checked every this many steps (the predicted steps are a
multiple of it)."""
NEVER = math.inf
"""Predicted steps of a run that does not settle."""
AUTO_MARGIN = 3.0
"""fpm.max_steps 'auto': this many times the predicted steps of the slowest load case (the
reduced step predicts 0.8-1.0 times the steps the runs take)."""
AUTO_MIN_STEPS = 1000
"""fpm.max_steps 'auto' is at least this."""
FALLBACK_STEPS = 20_000
"""fpm.max_steps 'auto' where there is no prediction (the paper method's joint search, a
lattice at rest that is a mechanism, a d that does not settle in the reduced step): the
default before 'auto'."""
SCHEMA_MAX_STEPS = 1_000_000
"""The schema's largest fpm.max_steps."""


def auto_max_steps(predicted: list[float] | float) -> int:
    """fpm.max_steps 'auto' from predicted steps (one per load case, or one): AUTO_MARGIN
    times the largest, at least AUTO_MIN_STEPS, at most SCHEMA_MAX_STEPS; FALLBACK_STEPS when
    one does not settle."""
    values = [float(p) for p in predicted] if isinstance(predicted, list) else [float(predicted)]
    if not values or not all(math.isfinite(v) for v in values):
        return FALLBACK_STEPS
    return int(min(SCHEMA_MAX_STEPS, max(AUTO_MIN_STEPS, math.ceil(AUTO_MARGIN * max(values)))))


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
        # (the gathered shapes of a piece are 4.8 MB per mode instead of 38)
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
    _powers: dict[float, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

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


@dataclass
class Prediction:
    """The fastest-settling d predicted from the modes, before any run.

    Attributes:
        d: the predicted fastest d, N s/m.
        steps: (L,) predicted steps per load case at d.
        radius: (L,) spectral radius of each case's reduced step at d.
        modes: modes per list (count, per distinct list).
        seconds: wall time of the modes and the prediction, s.
    """

    d: float
    steps: list[float]
    radius: list[float]
    modes: list[int]
    seconds: float = 0.0

    @property
    def total(self) -> float:
        return float(sum(self.steps))


def total_steps(models: list[StepModel], d: float, cap: int, budget: float = NEVER) -> float:
    """Predicted steps summed over the load cases at d; inf if one never settles, or once the
    sum passes ``budget``."""
    total = 0.0
    for model in models:
        total += model.steps(d, int(min(cap, budget - total + CHECK_EVERY)))
        if not total <= budget:
            return NEVER
    return total


def fastest_predicted(
    models: list[StepModel], bounds: tuple[float, float], cap: int, *, points: int = 25
) -> tuple[float, list[float]]:
    """The d in ``bounds`` (N s/m) with the fewest predicted steps summed over ``models``: a
    log grid of ``points`` (a point is given up once its sum passes twice the best so far),
    then golden-section refinement around its best to 0.5%. Returns (d, predicted steps per
    model). Raises ValueError if no d of the grid settles."""
    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    grid = np.linspace(lo, hi, points)
    totals: list[float] = []
    for y in grid:
        budget = 2 * min(totals, default=NEVER)
        totals.append(total_steps(models, math.exp(y), cap, budget))
    best = int(np.argmin(totals))
    if not math.isfinite(totals[best]):
        raise ValueError("no d in the bounds settles in the reduced step")
    a, b = grid[max(best - 1, 0)], grid[min(best + 1, points - 1)]
    golden = (math.sqrt(5) - 1) / 2
    known = {float(grid[best]): totals[best]}

    def value(y: float) -> float:
        if y not in known:
            known[y] = total_steps(models, math.exp(y), cap)
        return known[y]

    c, e = b - golden * (b - a), a + golden * (b - a)
    while b - a > math.log(1.005):
        if value(c) <= value(e):
            b, e = e, c
            c = b - golden * (b - a)
        else:
            a, c = c, e
            e = a + golden * (b - a)
    y = min(known, key=lambda v: (known[v], v))
    d = math.exp(y)
    return d, [m.steps(d, cap) for m in models]


def predict_damping(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    bounds: tuple[float, float],
    static: np.ndarray | None = None,
    *,
    cap: int = 1_000_000,
    count: int = MODES,
    distances: list[float] | None = None,
    modes: dict[bytes, Modes] | None = None,
) -> tuple[Prediction, list[StepModel]]:
    """The predicted fastest d of ``problem``'s load cases at ``stiffness``, ``depth`` and
    ``dt``, within ``bounds`` (N s/m), and the reduced steps it came from.

    ``solver``: the problem's static solver (its systems, perturbed lists and multigrid
    hierarchies); ``static`` (L, N, 3): the static equilibria, m (None: the modes' linear
    response); ``distances``: each case's settle distance towards them (None: the spec's,
    :func:`fpm.dynamics.settle.nominal_distance`). One set of modes per distinct list;
    ``modes``: those already found (:class:`fpm.dynamics.modes_ahead.ModesAhead`), keyed as
    :func:`reduced_steps` keys them.

    Raises:
        ValueError: no d in the bounds settles in the reduced steps (e.g. a tolerance of 0).
        SingularStiffnessError: the lattice at rest is not held (a mechanism).
    """
    t0 = time.perf_counter()
    found: dict[bytes, Modes] = {} if modes is None else dict(modes)
    with single_threaded_blas():
        models = reduced_steps(
            problem, solver, stiffness, depth, dt, static, count=count, modes=found,
            distances=distances,
        )  # fmt: skip
        d, steps = fastest_predicted(models, bounds, cap)
        radius = [m.radius(d) for m in models]
    prediction = Prediction(
        d=d,
        steps=steps,
        radius=radius,
        modes=[len(v.w2) for v in found.values()],
        seconds=time.perf_counter() - t0,
    )
    return prediction, models


def reduced_steps(
    problem: Problem,
    solver: StaticSolver,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    static: np.ndarray | None = None,
    *,
    count: int = MODES,
    cases: list[int] | None = None,
    modes: dict[bytes, Modes] | None = None,
    distances: list[float] | None = None,
) -> list[StepModel]:
    """:class:`StepModel` of each load case (``cases``: those only) at ``stiffness``,
    ``depth``, ``dt``; the modes of each distinct list computed once and kept in ``modes``
    (keyed by the list's nodes; pass the same dict again for the same stiffness). On the
    distance criteria of :mod:`fpm.dynamics.settle`: with ``static`` (L, N, 3) m the target
    criterion at ``distances`` (None: the spec's nominal distance), else the bound (1) at
    the nominal distance.

    Raises:
        SingularStiffnessError: the lattice at rest has a mode without stiffness.
    """
    found = {} if modes is None else modes
    spec = problem.spec
    models = []
    for j in range(len(problem.load_cases)) if cases is None else cases:
        system, _ = solver.system(j, depth)
        key = system.free.tobytes()
        params = system.parameters(stiffness)
        if key not in found:
            kept = solver.multigrid(system) if 3 * system.n_free > DENSE_UP_TO else None
            hierarchy = None
            if kept is not None:
                # above DENSE_UP_TO the modes read the hierarchy's own levels (the finest
                # level's matrix is the stiffness), so the tangent at rest, 0.18 GB on the
                # 93,705-node organ, is assembled only where there is no hierarchy yet
                hierarchy = kept.hierarchy
                tangent = hierarchy.levels[0].A
            else:
                tangent = system.tangent(np.zeros((system.n_free, 3)), params, modified=True)
                if 3 * system.n_free > DENSE_UP_TO:
                    hierarchy = solver._linear_hierarchy(system, tangent).hierarchy
            try:
                lowest = lowest_modes(
                    tangent, problem.solid.masses[system.free], count, hierarchy=hierarchy,
                    free=system.free,
                )  # fmt: skip
            except np.linalg.LinAlgError as e:
                raise SingularStiffnessError(f"the modes: {e}") from None
            found[key] = lowest
        if not np.all(found[key].w2 > 1e-12 * max(float(found[key].w2.max()), 1e-300)):
            raise SingularStiffnessError("the lattice at rest has a mode without stiffness")
        plist = solver.lists.get(problem.load_cases[j].nodes, depth)
        loads = solver.loads(j)
        distance = by_distance(spec)
        if distance:  # fpm.dynamics.settle: (1) at the modes' response, or (2) at static's
            shapes = found[key]
            if static is None:  # the modes' linear response, on the distance criterion (1)
                f = loads[system.free].ravel()
                moved = shapes.shapes @ ((shapes.shapes.T @ f) / shapes.w2)
                force = (
                    nominal_distance(spec)
                    * mode_stiffness(shapes.w2, shapes.shapes)
                    * float(np.linalg.norm(moved))
                )
            else:  # the target criterion (2): its reach, m
                share = nominal_distance(spec) if distances is None else distances[j]
                force = share * nodal_size(static[j])
        else:
            force = force_tolerance(spec) * float(np.linalg.norm(loads[plist.order], axis=1).max())
        models.append(
            step_model(
                system,
                stiffness,
                plist.order,
                found[key],
                problem.solid.masses,
                dt,
                loads,
                force,
                None if static is None else static[j],
                distance,
            )  # fmt: skip
        )
    return models


def fixed_max_steps(value: int | str) -> int:
    """fpm.max_steps where nothing predicts it: the number, or FALLBACK_STEPS for 'auto'."""
    return FALLBACK_STEPS if value == "auto" else int(value)


def case_models(
    problem: Problem,
    stiffness: Stiffness,
    depth: int | None,
    dt: float,
    cases: list[int] | None = None,
) -> list[StepModel] | None:
    """The reduced steps of ``cases`` (None: every load case) at (``stiffness``, ``depth``,
    ``dt`` s), each starting from the modes' linear response; None where there are none (the
    lattice at rest a mechanism). The modes of the last stiffness asked for are kept on the
    problem (``problem.cache["modes"]``)."""
    from .equilibrium import static_solver

    key = (stiffness.parameters().tobytes(), depth)
    kept = problem.cache.get("modes")
    if kept is None or kept[0] != key:
        kept = problem.cache["modes"] = (key, {})
    try:
        with single_threaded_blas():
            return reduced_steps(
                problem, static_solver(problem), stiffness, depth, dt, cases=cases, modes=kept[1]
            )
    except (SingularStiffnessError, ValueError, ArithmeticError):
        return None


def predicted_max_steps(
    problem: Problem,
    stiffness: Stiffness,
    d: float,
    depth: int | None,
    dt: float,
    cases: list[int] | None = None,
) -> int:
    """fpm.max_steps 'auto' for runs at (``stiffness``, ``d`` N s/m, ``depth``, ``dt`` s) of
    ``cases`` (None: every load case): :func:`auto_max_steps` of the reduced steps'
    (:func:`case_models`) prediction at d; FALLBACK_STEPS where there is none (the lattice at
    rest a mechanism, d not settling)."""
    models = case_models(problem, stiffness, depth, dt, cases)
    if models is None:
        return FALLBACK_STEPS
    with single_threaded_blas():
        return auto_max_steps([m.steps(d, SCHEMA_MAX_STEPS) for m in models])
