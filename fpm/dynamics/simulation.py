"""FPM simulation of one load case (paper Sec. 3.2): the Python API around the compiled step."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..model.forces import Stiffness, cells
from ..model.perturbed_list import Adjacency, ListLayout, PerturbedList, PerturbedListCache
from ..model.problem import Problem
from ..model.spec import FpmSettings
from ..model.stiffness import axis_factors, has_volume, model_stiffness
from ..model.volume import Cells
from .settle import SettleCriterion, by_distance, force_tolerance, nominal_distance
from .stability import auto_time_step
from .voigt import DIVERGED, INVERTED, RUNNING, SETTLED, run_steps


@dataclass
class SimulationResult:
    """Outcome of one FPM run of one load case.

    Attributes:
        nodes: (N, 3) rest positions, m.
        displacements: (N, 3) final displacements, m (zero outside the perturbed list).
        steps: time steps taken.
        settled: the run reached equilibrium within max_steps (physics.md criterion).
        diverged: positions became non-finite or moved further than the solid's size, or a
            cell inverted.
        perturbed: number of nodes in the perturbed list.
        depth: layers actually reached (<= the depth asked for).
        residual: largest unbalanced nodal force |F_i + F_s| in the last sweep, N.
        load_case: index of the load case.
        inverted_cell: the cell (hexahedron index) whose volume reached zero, or None.
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
    inverted_cell: int | None = None

    @property
    def message(self) -> str:
        """Why the run stopped short of settling ("" if it settled or is still running)."""
        if self.inverted_cell is not None:
            return (
                f"load case {self.load_case}: cell {self.inverted_cell} (hexahedron index) "
                f"inverted at step {self.steps}: its volume reached zero; the load is too large "
                "for this lattice, or dt is too long (try a smaller fpm.dt)"
            )
        if self.diverged:
            return (
                f"load case {self.load_case}: diverged at step {self.steps} (a node left the "
                "solid's size or became non-finite): lower fpm.dt or raise d"
            )
        return ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (arrays as nested lists)."""
        out = asdict(self)
        out["nodes"] = self.nodes.tolist()
        out["displacements"] = self.displacements.tolist()
        return out


class FpmModel:
    """A problem's FPM arrays, built once: neighbours, perturbed lists and their layouts
    (:class:`~fpm.model.perturbed_list.ListLayout`), work buffers.

    Attributes:
        problem: the problem.
        adjacency: spring neighbours (:class:`fpm.model.perturbed_list.Adjacency`).
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
        self._cells: dict[bytes, tuple[Cells, np.ndarray]] = {}
        self._layouts: dict[bytes, ListLayout] = {}
        self._local_cells: dict[bytes, Cells] = {}
        gravity = np.asarray(problem.spec.fpm.gravity, dtype=float)
        self._weight = solid.masses[:, None] * gravity[None, :] if np.any(gravity) else None

    def perturbed_list(self, load_case: int, depth: int | None) -> PerturbedList:
        """The (cached) list of ``load_case`` for ``depth`` layers (None = all reachable)."""
        return self.lists.get(self.problem.load_cases[load_case].nodes, depth)

    def active_cells(self, plist: PerturbedList) -> tuple[Cells, np.ndarray]:
        """The cells with a corner in ``plist`` (only they can move) and their indices (C,)
        among the solid's hexahedra; kept per list."""
        key = plist.order.tobytes()
        found = self._cells.get(key)
        if found is None:
            every = cells(self.problem)
            listed = np.zeros(self.problem.n_nodes, dtype=bool)
            listed[plist.order] = True
            which = np.flatnonzero(listed[every.corners].any(axis=1))
            found = self._cells[key] = (every.subset(which), which)
        return found

    def layout(self, plist: PerturbedList) -> ListLayout:
        """``plist``'s own numbering of the nodes; kept per list."""
        key = plist.order.tobytes()
        found = self._layouts.get(key)
        if found is None:
            found = self._layouts[key] = ListLayout.of(self.adjacency, plist)
        return found

    def local_cells(self, plist: PerturbedList) -> Cells:
        """:meth:`active_cells` with their corners in ``plist``'s own numbering; kept per list."""
        key = plist.order.tobytes()
        found = self._local_cells.get(key)
        if found is None:
            active, _ = self.active_cells(plist)
            corners = np.ascontiguousarray(self.layout(plist).local[active.corners])
            found = self._local_cells[key] = Cells(corners, active.rest, active.volume)
        return found

    def run(
        self,
        load_case: int,
        *,
        k: float | np.ndarray | Stiffness,
        d: float,
        depth: int | None,
        dt: float,
        max_steps: int,
        settle: SettleCriterion | None = None,
        settle_tolerance: float | None = None,
    ) -> SimulationResult:
        """Simulate ``load_case`` from rest; see :func:`simulate`.

        ``k`` is one stiffness for every spring (scaled by the spec's stiffness_scale), N/m,
        the (S,) stiffness of every spring (:func:`fpm.model.stiffness.spring_stiffness`, scale
        included), or the model's :class:`~fpm.model.forces.Stiffness` (springs and volume).
        """
        run = self.start(
            load_case, k=k, d=d, depth=depth, dt=dt, settle=settle,
            settle_tolerance=settle_tolerance,
        )  # fmt: skip
        run.advance(max_steps, buffers=(self._x, self._v))
        return run.result()

    def start(
        self,
        load_case: int,
        *,
        k: float | np.ndarray | Stiffness,
        d: float,
        depth: int | None,
        dt: float,
        settle: SettleCriterion | None = None,
        settle_tolerance: float | None = None,
    ) -> DynamicRun:
        """A run of ``load_case`` from rest that advances in pieces (:class:`DynamicRun`);
        arguments as :meth:`run`. It settles on ``settle``
        (:class:`~fpm.dynamics.settle.SettleCriterion`), or, given ``settle_tolerance`` in its
        place, on the force criterion at that tolerance (0 never settles); exactly one of the
        two."""
        if (settle is None) == (settle_tolerance is None):
            raise ValueError("give exactly one of settle and settle_tolerance")
        if settle is None:
            settle = SettleCriterion(force_tolerance=settle_tolerance)
        p = self.problem
        plist = self.perturbed_list(load_case, depth)
        external = p.load_cases[load_case].dense(p.n_nodes)
        if self._weight is not None:
            external += self._weight
        layout = self.layout(plist)
        factor = layout.rows.stiffness_factor
        kappa: np.ndarray | None = None
        if isinstance(k, Stiffness):
            kappa = k.volume
            k = k.springs
        if np.ndim(k):  # per-spring stiffness: the kernel's factor carries it, with k = 1
            factor, k = np.asarray(k, dtype=float)[layout.rows.spring], 1.0
        if kappa is not None:
            which = self.active_cells(plist)[1]
            volume = (self.local_cells(plist), np.ascontiguousarray(kappa[which], dtype=float))
        else:
            volume = (_NO_CELLS, np.zeros(0))
        return DynamicRun(
            model=self,
            load_case=load_case,
            plist=plist,
            layout=layout,
            external=external,
            factor=factor,
            k=float(k),
            d=float(d),
            dt=float(dt),
            settle=settle,
            volume=volume,
        )


_NO_CELLS = Cells(np.zeros((0, 8), dtype=np.int64), np.zeros((0, 6, 3)), np.zeros(0))


class DynamicRun:
    """One load case simulated from rest, advanced in pieces: ``advance(n)`` continues exactly
    where the last piece stopped (the state is x and v), so a caller can stop runs that can no
    longer matter (the damping search stops a d once its steps exceed the best total).

    The kernel runs on the list's own numbering (``layout``): x and v, and the rest positions,
    masses and forces it reads, are kept in it; :meth:`result` gives them back in the solid's.

    Attributes:
        steps: time steps taken so far.
        state: voigt.RUNNING, SETTLED or DIVERGED.
        residual: what the settle test reads of the last sweep: the largest unbalanced nodal
            force, N (the force criterion), their 2-norm over the list, N (the distance
            criterion, ``settle_stiffness`` > 0), or its reach from the static equilibrium, m
            (the target criterion, a ``target`` given).
        moved: the 2-norm of the last sweep's nodal displacements over the list, m.
        settle_force: the residual the run settles below where it stands: the force
            criterion's (N), ``settle_stiffness`` (N/m) times ``moved``, or ``reach`` (m).
        history: (steps, residual) after every piece, for a caller that watches the decay.
    """

    def __init__(
        self,
        *,
        model: FpmModel,
        load_case: int,
        plist: PerturbedList,
        layout: ListLayout,
        external: np.ndarray,
        factor: np.ndarray,
        k: float,
        d: float,
        dt: float,
        settle: SettleCriterion,
        volume: tuple[Cells, np.ndarray],
    ):
        p = model.problem
        self.cells, self.kappa = volume
        self.inverted_cell: int | None = None
        self.model, self.load_case, self.plist, self.layout = model, load_case, plist, layout
        self.external, self.factor = np.ascontiguousarray(external[layout.nodes]), factor
        self.k, self.d, self.dt = k, d, dt
        # The criterion as the kernel's scalars: 0 (and a (0, 3) target) for a criterion unused.
        settle_force = 0.0
        if settle.force_tolerance is not None:
            applied = float(np.linalg.norm(external[plist.order], axis=1).max())
            settle_force = float(settle.force_tolerance) * applied
        self.settle_stiffness = 0.0 if settle.stiffness is None else float(settle.stiffness)
        self.settle_force, self.moved = settle_force, 0.0
        self._force_criterion = settle_force
        self.x: np.ndarray | None = None  # own buffers, made on the first piece
        self.v: np.ndarray | None = None
        self.steps, self.state, self.residual = 0, RUNNING, 0.0
        self.history: list[tuple[int, float]] = []
        self._rest = np.ascontiguousarray(p.nodes[layout.nodes])
        self._mass = np.ascontiguousarray(p.solid.masses[layout.nodes])
        self._force: np.ndarray | None = None  # volume forces (N, 3), made on the first piece
        self._target = np.zeros((0, 3))
        self.slowness, self._reach = 0.0, 0.0
        if settle.target is not None:  # the static equilibrium's positions, list's numbering
            self._target = np.ascontiguousarray(self._rest + settle.target[layout.nodes])
            self.slowness = float(settle.slowness)  # type: ignore[arg-type]
            self.settle_force = self._reach = float(settle.reach)  # type: ignore[arg-type]

    @property
    def diverged(self) -> bool:
        """Diverged, or a cell inverted."""
        return self.state in (DIVERGED, INVERTED)

    @property
    def finished(self) -> bool:
        """Settled or diverged."""
        return self.state != RUNNING

    def advance(self, steps: int, *, buffers: tuple[np.ndarray, np.ndarray] | None = None) -> bool:
        """Up to ``steps`` more time steps (fewer once settled or diverged); True once finished.
        ``buffers``: (N, 3) x and v arrays to use (from rest) instead of new ones (their
        content is in the list's numbering)."""
        if self.finished or steps < 1:
            return self.finished
        if self.x is None or self.v is None:
            self.x, self.v = buffers or (np.empty_like(self._rest), np.empty_like(self._rest))
            self.x[:] = self._rest
            self.v[:] = 0.0
        a, p, c = self.layout.rows, self.model.problem, self.cells
        if self._force is None:
            self._force = np.zeros_like(self._rest) if len(c.volume) else np.zeros((0, 3))
        taken, self.state, worst, inverted, norm, moved = run_steps(
            self.layout.order, a.ptr, a.neighbour, a.rest_length, self.factor, self._rest,
            self.x, self.v, self.external, self._mass, self.k, self.d, self.dt,
            int(steps), self._force_criterion, self.settle_stiffness, p.size,
            c.corners, c.rest, c.volume, self.kappa, self._force, self._target, self.slowness,
            self._reach,
        )  # fmt: skip
        self.moved = float(moved)
        if len(self._target):
            self.residual = float(norm)
        elif self.settle_stiffness > 0:
            self.residual, self.settle_force = float(norm), self.settle_stiffness * self.moved
        else:
            self.residual = float(worst)
        self.steps += int(taken)
        self.history.append((self.steps, float(self.residual)))
        if inverted >= 0:
            self.inverted_cell = int(self.model.active_cells(self.plist)[1][inverted])
        return self.finished

    def result(self) -> SimulationResult:
        """Where the run stands, as a :class:`SimulationResult` (displacements copied)."""
        p = self.model.problem
        x = p.nodes if self.x is None else self.x[self.layout.local]
        return SimulationResult(
            nodes=p.nodes,
            displacements=x - p.nodes,
            steps=self.steps,
            settled=self.state == SETTLED,
            diverged=self.diverged,
            perturbed=len(self.plist.order),
            depth=self.plist.layers,
            residual=float(self.residual),
            load_case=self.load_case,
            inverted_cell=self.inverted_cell,
        )


def fpm_model(problem: Problem) -> FpmModel:
    """The problem's :class:`FpmModel`, built on first use and kept on the problem."""
    model = problem.cache.fpm_model
    if model is None:
        model = problem.cache.fpm_model = FpmModel(problem)
    return model


def simulate(
    problem: Problem,
    *,
    k: float | Sequence[float] | Stiffness,
    d: float,
    depth: int | None = None,
    load_case: int = 0,
    dt: float | str | None = None,
    max_steps: int | None = None,
    settle_tolerance: float | None = None,
) -> SimulationResult:
    """Run the FPM for one load case from rest.

    Args:
        problem: from :func:`fpm.load_problem`.
        k: the fitted stiffness parameters: one k for every spring (N/m), or one per spring
            family, then kappa (Pa) for families+volume (:mod:`fpm.model.stiffness`); or the
            model's :class:`~fpm.model.forces.Stiffness` itself (a field fit's, every spring's
            and cell's own).
        d: nodal damping, N s/m.
        depth: penetration depth in layers; None = the spec's ('full' and 'auto' mean all layers).
        load_case: index into the spec's load cases.
        dt, max_steps, settle_tolerance: None = the spec's value (dt 'auto': half the
            lattice's stability estimate at k, at most 1 ms; max_steps 'auto': three times the
            steps the lattice's slowest modes predict at k and d,
            :func:`fpm.dynamics.modes.predicted_max_steps`); ``settle_tolerance=0`` never
            settles. Where neither names a settle_tolerance, the run settles on the spec's
            settle_distance (:mod:`fpm.dynamics.settle`; the force criterion at
            :data:`~fpm.dynamics.settle.FORCE_TOLERANCE` for the paper method or a lattice
            that is a mechanism at rest).
    """
    s = problem.spec.fpm
    if not 0 <= load_case < len(problem.load_cases):
        raise ValueError(f"load_case must be in 0..{len(problem.load_cases) - 1}")
    springs = k.springs if isinstance(k, Stiffness) else np.asarray(k)
    if not (np.all(springs > 0) and d >= 0):
        raise ValueError("need k > 0 and d >= 0")
    stiffness: float | Stiffness = (
        model_stiffness(problem, k)  # type: ignore[arg-type]
        if isinstance(k, Stiffness) or np.ndim(k) or has_volume(problem)
        else float(k)  # type: ignore[arg-type]
    )
    if depth is None:
        depth = s.layers
    # Overrides pass the schema's own checks (dt > 0, max_steps >= 1, depth >= 0, ...).
    given = {"dt": dt, "max_steps": max_steps, "settle_tolerance": settle_tolerance}
    if depth is not None:
        given["depth"] = depth
    settings = FpmSettings.model_validate(
        s.model_dump() | {key: v for key, v in given.items() if v is not None}
    )
    step = auto_time_step(problem, stiffness) if settings.dt == "auto" else float(settings.dt)
    cap, tolerance = settings.max_steps, settings.settle_tolerance
    distance = tolerance is None and by_distance(problem.spec)
    models = None
    if cap == "auto" or distance:  # from the lattice's slowest modes (fpm.dynamics.modes)
        from .step_caps import FALLBACK_STEPS, SCHEMA_MAX_STEPS, auto_max_steps, case_models

        model = stiffness if isinstance(stiffness, Stiffness) else model_stiffness(problem, k)
        models = case_models(problem, model, depth, step, [load_case])
    if distance and models is not None:
        settle = SettleCriterion(
            stiffness=nominal_distance(problem.spec) * models[0].mode_stiffness
        )
    elif tolerance is None:  # the paper method, or a lattice with no modes at rest
        settle = SettleCriterion(force_tolerance=force_tolerance(problem.spec))
    else:
        settle = SettleCriterion(force_tolerance=tolerance)
    if cap == "auto":
        cap = auto_max_steps([models[0].steps(d, SCHEMA_MAX_STEPS)]) if models else FALLBACK_STEPS
    return fpm_model(problem).run(
        load_case,
        k=stiffness,
        d=d,
        depth=depth,
        dt=step,
        max_steps=int(cap),
        settle=settle,
    )
