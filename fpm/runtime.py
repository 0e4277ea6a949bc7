"""The fitted model as an engine runs it: the JSON export stepped with forces that change each step.

:class:`Runtime` needs nothing but the export (``fpmcal export --format json`` or the service's
``/v1/parameter-sets/{id}/export``): no spec, no calibration, no compiled kernel; NumPy only, so
that it is the recipe another engine ports (the web view's live model does, in JavaScript).

One step, every node at once (positions x, velocities v, both (N, 3); masses m (N,); the fixed
nodes never move)::

    F = F_ext + m g + F_springs(x) + F_volume(x)              (N, 3), N
    v <- (v + dt F / m) / (1 + dt d / m)                        damping taken implicitly
    x <- x + dt v

with, from the export's energy (its ``energy`` field),

- springs s = (i, j, L, k): ``f = k (|r| - L) r / |r|`` on i and ``-f`` on j, r = x_j - x_i;
- the volume term, per hexahedron c with corners in :data:`NATURAL` order: ``f_n = -kappa_c
  (V_c - V0_c) / V0_c dV_c/dx_n``, V_c the volume of the trilinear hexahedron in closed form,
  ``V = 8 [a1, a2, a3] + 8/3 ([a1, a4, a5] + [a4, a2, a6] + [a5, a6, a3])`` with
  ``a_k = sum_n C_kn x_n`` (:data:`COEFFICIENTS`) and [a, b, c] = a . (b x c).

The calibration's own kernel (:mod:`fpm.dynamics.voigt`) visits the perturbed list node by node,
each node seeing its predecessors' new positions, and moves only the list; an engine moves every
node at once. Both rest at the same static equilibrium (dE/dx = 0 over the free nodes), which
the tests check against :func:`fpm.simulate` to 1e-9; at the fitted dt the all-at-once step is
the more stable of the two (docs/physics.md, *Engines*).

Which d and dt: the export's ``parameters.d`` and ``dt`` are the fastest-settling ones of the
calibration's kernel; its ``parameters.engine`` block holds those of this step
(:mod:`fpm.dynamics.engine_damping`: fewer steps to the same equilibrium).
:meth:`Runtime.from_export` steps at the engine's when the export carries them
(``damping="engine"``, the default) and at the kernel's with ``damping="kernel"`` (or when an
older export has no engine block).

The paper's tunable speed (Sec. 3.1): :meth:`Runtime.region` is the runtime of one load's
perturbed list up to a depth (every node beyond held at rest), so a step costs what the list
holds, not the lattice; the export's ``parameters.depth`` is its default. Within the list it is
the all-at-once step above; it rests where the calibration's kernel rests at that depth.

This file is the recipe, in NumPy. :meth:`Runtime.step` runs it compiled where it can
(``backend``, :mod:`fpm.native`): the C step of ``fpm/native/fpm_step.c``, compiled on first
use with the system's C compiler, else the same arithmetic in numba, else this NumPy; in
float64 each equals the recipe to rounding (docs/reference/native-step.md).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

NATURAL = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
    dtype=float,
)  # fmt: skip
"""(8, 3) the natural coordinates (r, s, t) of a hexahedron's corners, in the export's order."""

COEFFICIENTS = (
    np.stack(
        [
            NATURAL[:, 0],
            NATURAL[:, 1],
            NATURAL[:, 2],
            NATURAL[:, 0] * NATURAL[:, 1],
            NATURAL[:, 0] * NATURAL[:, 2],
            NATURAL[:, 1] * NATURAL[:, 2],
        ]
    )
    / 8.0
)
"""(6, 8) C_kn: a_k = sum_n C_kn x_n, the coefficients of r, s, t, rs, rt, st in the trilinear
map x(r, s, t) of a hexahedron."""

TRIPLES = ((0, 1, 2, 8.0), (0, 3, 4, 8.0 / 3.0), (3, 1, 5, 8.0 / 3.0), (4, 5, 2, 8.0 / 3.0))
"""The volume as weighted triple products of a1..a6 (0-based): (p, q, r, weight)."""


class ExportFormatError(ValueError):
    """The document is not an FPM lattice export this runtime can step."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (3, C) arrays (components first: plain arithmetic, no np.cross)."""
    return np.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def hexahedron_volumes(x: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Volumes (C,) m^3 of the trilinear hexahedra ``corners`` (C, 8) at positions ``x`` (N, 3),
    and their gradients dV/dx (C, 8, 3), m^2 (exact: V is linear in each corner)."""
    # einsum's own loops, not BLAS: a multithreaded BLAS call leaves its threads spinning, which
    # starves the native step's threads in an engine's loop (bench native, part probe)
    a = np.einsum("kn,cnd->kdc", COEFFICIENTS, x[corners])  # (6, 3, C): a_k, component, cell
    volume = np.zeros(len(corners))
    grad_a = np.zeros_like(a)
    for p, q, r, w in TRIPLES:
        qr = _cross(a[q], a[r])
        volume += w * (a[p] * qr).sum(axis=0)
        grad_a[p] += w * qr
        grad_a[q] += w * _cross(a[r], a[p])
        grad_a[r] += w * _cross(a[p], a[q])
    grad = np.einsum("kn,kdc->ndc", COEFFICIENTS, grad_a)  # (8, 3, C)
    return volume, grad.transpose(2, 0, 1)


@dataclass
class Runtime:
    """An exported FPM lattice, stepped in time.

    Attributes:
        rest: (N, 3) rest positions, m.
        masses: (N,) lumped masses, kg.
        fixed: (N,) bool, the nodes that never move.
        springs: (S, 2) node indices i, j.
        rest_lengths: (S,) m.
        stiffness: (S,) N/m, each spring's own.
        hexahedra: (H, 8) corner indices (NATURAL order), or (0, 8) without the volume term.
        kappa: (H,) volume stiffness per hexahedron, Pa.
        rest_volumes: (H,) m^3.
        d: nodal damping, N s/m.
        dt: time step, s.
        damping: where d and dt came from: ``"kernel"`` (the export's ``parameters.d`` and
            ``dt``, the calibration kernel's), ``"engine"`` (its ``parameters.engine``, this
            step's fastest-settling ones) or ``"given"`` (set by the caller).
        settle_tolerance: settled when the largest unbalanced nodal force is below this times
            the largest applied nodal force (of the step, or of the last loaded step when the
            forces are zero).
        settle_stiffness: or when the 2-norm of the unbalanced nodal forces is below this
            (N/m) times the 2-norm of the displacements (of the step, or of the last loaded
            step when the forces are zero: the equilibrium is then rest) (the distance
            criterion, :mod:`fpm.dynamics.settle`; 0: none).
        gravity: (3,) m/s^2 (the weight m g joins the applied forces).
        shares: (N, N) sparse, for an export fitted with ``loads: "hat"``: row i the shares of
            a force on surface node i (the export's ``load_shares``); None: forces act at their
            node (:meth:`applied`).
        backend: how :meth:`step` runs: ``"native"`` (the C step), ``"numba"``, ``"numpy"``
            (this recipe) or ``"auto"`` (the first that works); None: the environment's
            ``FPM_RUNTIME_BACKEND``, else ``"auto"``. ``backend_used`` says which ran.
        precision: ``"float64"``, or ``"float32"`` (the C step only: x and v are then float32).
        depth: the export's penetration depth, layers (None: every layer), what
            :meth:`region` cuts at unless told otherwise.
        x, v: (N, 3) positions (m) and velocities (m/s), the state :meth:`step` advances.
        steps: steps taken since the last :meth:`reset`.
        unbalanced: the largest |F_i| over the free nodes at the start of the last step, N.
        settled: whether ``unbalanced`` was under the settle tolerance.
    """

    rest: np.ndarray
    masses: np.ndarray
    fixed: np.ndarray
    springs: np.ndarray
    rest_lengths: np.ndarray
    stiffness: np.ndarray
    hexahedra: np.ndarray
    kappa: np.ndarray
    rest_volumes: np.ndarray
    d: float
    dt: float
    settle_tolerance: float
    settle_stiffness: float = 0.0
    damping: str = "given"
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    shares: sp.csr_matrix | None = None
    backend: str | None = None
    precision: str = "float64"
    depth: int | None = None
    backend_used: str = field(init=False, default="numpy")
    x: np.ndarray = field(init=False)
    v: np.ndarray = field(init=False)
    steps: int = field(init=False, default=0)
    unbalanced: float = field(init=False, default=float("inf"))
    settled: bool = field(init=False, default=False)
    _load_scale: float = field(init=False, default=0.0, repr=False)
    _moved_scale: float = field(init=False, default=0.0, repr=False)
    _shared: np.ndarray | None = field(init=False, default=None, repr=False)
    _engine: Any = field(init=False, default=None, repr=False)
    _x_next: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n, s = self.n_nodes, len(self.springs)
        # Gathering the forces onto the nodes as sparse products: (N, S) with +1 at (i, s) and
        # -1 at (j, s) for the springs, (N, 8 H) with 1 at (corner, slot) for the hexahedra.
        rows = np.concatenate([self.springs[:, 0], self.springs[:, 1]])
        signs = np.concatenate([np.ones(s), -np.ones(s)])
        self._spring_scatter = sp.csr_matrix((signs, (rows, np.tile(np.arange(s), 2))), (n, s))
        flat = self.hexahedra.ravel()
        self._corner_scatter = sp.csr_matrix(
            (np.ones(len(flat)), (flat, np.arange(len(flat)))), (n, len(flat))
        )
        # the nodes whose force is shared (rows of load_shares), (N, 1) bool
        self._shared = None if self.shares is None else (np.diff(self.shares.indptr) > 0)[:, None]
        backend = self.backend or os.environ.get("FPM_RUNTIME_BACKEND") or "auto"
        if backend != "numpy" or self.precision != "float64":
            from .native import engine

            self._engine = engine(self, backend, self.precision)
        self.backend_used = "numpy" if self._engine is None else self._engine.name
        self.reset()

    @classmethod
    def from_export(
        cls,
        export: dict[str, Any] | str | Path,
        backend: str | None = None,
        precision: str = "float64",
        damping: str | None = None,
    ) -> Runtime:
        """The runtime of a JSON export (the parsed dict, or the path of the file), stepped by
        ``backend`` in ``precision`` (the attributes').

        ``damping``: ``"engine"``, the d and dt of the export's ``parameters.engine`` (this
        step's fastest-settling ones; an export without that block is refused), ``"kernel"``,
        its ``parameters.d`` and ``dt`` (the calibration kernel's), or None: the engine's where
        the export carries them, else the kernel's. ``damping`` on the runtime says which."""
        doc = export if isinstance(export, dict) else json.loads(Path(export).read_text())
        if doc.get("format") != "fpm-lattice":
            raise ExportFormatError("not an FPM lattice export (its format is not 'fpm-lattice')")
        p = doc["parameters"]
        engine = p.get("engine")
        if damping is None:
            damping = "engine" if engine else "kernel"
        if damping not in ("engine", "kernel"):
            raise ValueError(f"damping: 'engine' or 'kernel', not {damping!r}")
        if damping == "engine" and not engine:
            raise ExportFormatError(
                "this export has no parameters.engine block (an export made before it was "
                "added, or one whose engine damping could not be computed): step it with "
                "damping='kernel', or fpm.dynamics.engine_damping.with_engine_damping"
            )
        chosen = engine if damping == "engine" else p
        nodes = np.asarray(doc["nodes"], dtype=float).reshape(-1, 3)
        springs = np.asarray(doc["springs"], dtype=float).reshape(-1, 4)
        fixed = np.zeros(len(nodes), dtype=bool)
        fixed[np.asarray(doc["fixed"], dtype=np.int64)] = True
        if doc.get("volume_stiffness") is not None:
            hexahedra = np.asarray(doc["hexahedra"], dtype=np.int64).reshape(-1, 8)
            kappa = np.asarray(doc["volume_stiffness"], dtype=float)
            rest_volumes = np.asarray(doc["rest_volumes"], dtype=float)
        else:
            hexahedra, kappa, rest_volumes = np.zeros((0, 8), np.int64), np.zeros(0), np.zeros(0)
        shares, table = None, doc.get("load_shares")
        if table is not None:
            rows = np.repeat(np.asarray(table["nodes"], dtype=np.int64), np.diff(table["indptr"]))
            shares = sp.csr_matrix(
                (np.asarray(table["weights"], dtype=float), (rows, table["indices"])),
                (len(nodes), len(nodes)),
            )
        return cls(
            rest=nodes,
            masses=np.asarray(doc["masses"], dtype=float),
            fixed=fixed,
            springs=springs[:, :2].astype(np.int64),
            rest_lengths=springs[:, 2].copy(),
            stiffness=springs[:, 3].copy(),
            hexahedra=hexahedra,
            kappa=kappa,
            rest_volumes=rest_volumes,
            d=float(chosen["d"]),
            dt=float(chosen["dt"]),
            settle_tolerance=float(p["settle_tolerance"]),
            settle_stiffness=float(p.get("settle_stiffness", 0.0)),
            damping=damping,
            gravity=np.asarray(p.get("gravity", (0.0, 0.0, 0.0)), dtype=float),
            shares=shares,
            backend=backend,
            precision=precision,
            depth=None if p.get("depth") is None else int(p["depth"]),
        )

    @property
    def n_nodes(self) -> int:
        return len(self.rest)

    def reset(self) -> None:
        """Back to rest: x = the rest positions, v = 0."""
        dtype = np.float64 if self._engine is None else self._engine.dtype
        self.x = self.rest.astype(dtype)
        self.v = np.zeros_like(self.x)
        self._x_next = np.empty_like(self.x)
        if self._engine is not None:
            self._engine.reset()
        self.steps, self.unbalanced, self.settled, self._load_scale = 0, float("inf"), False, 0.0
        self._moved_scale = 0.0

    def applied(self, forces: np.ndarray) -> np.ndarray:
        """(N, 3) nodal ``forces`` (N, 3), N, as the fit applied them (the export's ``loads``):
        with ``"hat"`` a force on a surface node is shared over the nodes around it (its
        ``load_shares``); otherwise, and on interior nodes, as given. An engine passes the
        force of a tool at a node through this to get the model the fit judged."""
        f = np.asarray(forces, dtype=float).reshape(self.rest.shape)
        if self.shares is None or self._shared is None:
            return f
        shared = self._shared
        return np.asarray(self.shares.T @ np.where(shared, f, 0.0)) + np.where(shared, 0.0, f)

    def load_case_forces(self, export: dict[str, Any], case: int) -> np.ndarray:
        """(N, 3) the nodal forces of the export's load case ``case``, N."""
        c = export["load_cases"][case]
        forces = np.zeros_like(self.rest)
        forces[np.asarray(c["nodes"], dtype=np.int64)] = np.asarray(c["forces"], dtype=float)
        return forces

    def internal_forces(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) spring and volume forces at positions ``x`` (N, 3), N: -dE/dx of the model's
        energy without the applied forces."""
        i, j = self.springs[:, 0], self.springs[:, 1]
        r = x[j] - x[i]
        length = np.sqrt(np.einsum("sd,sd->s", r, r))
        f = (self.stiffness * (length - self.rest_lengths) / length)[:, None] * r
        out = self._spring_scatter @ f
        if len(self.hexahedra):
            volume, grad = hexahedron_volumes(x, self.hexahedra)
            pressure = self.kappa * (volume - self.rest_volumes) / self.rest_volumes
            corner_forces = -pressure[:, None, None] * grad  # (H, 8, 3)
            out += self._corner_scatter @ corner_forces.reshape(-1, 3)
        return np.asarray(out)

    def energy(self, x: np.ndarray, forces: np.ndarray | None = None) -> float:
        """The model's energy at positions ``x``, J (the export's ``energy``): springs, volume
        term, minus the work of ``forces`` (N, 3) and of gravity."""
        r = x[self.springs[:, 1]] - x[self.springs[:, 0]]
        stretch = np.linalg.norm(r, axis=1) - self.rest_lengths
        e = 0.5 * float(np.sum(self.stiffness * stretch**2))
        if len(self.hexahedra):
            volume, _ = hexahedron_volumes(x, self.hexahedra)
            change = volume - self.rest_volumes
            e += 0.5 * float(np.sum(self.kappa * change**2 / self.rest_volumes))
        applied = self.masses[:, None] * self.gravity[None, :]
        if forces is not None:
            applied = applied + forces
        return e - float(np.sum(applied * (x - self.rest)))

    def step(self, forces: np.ndarray | None = None) -> np.ndarray:
        """Advance one step under the external nodal ``forces`` (N, 3), N (None: none).

        Returns:
            (N, 3) the positions after the step, m (the runtime's own array: read, don't write).
        """
        if self._engine is not None:
            f = None
            if forces is not None:
                f = np.ascontiguousarray(forces, dtype=self._engine.dtype).reshape(self.x.shape)
            self.unbalanced, self.settled = self._engine.step(self.x, self._x_next, self.v, f)
            self.x, self._x_next = self._x_next, self.x
            self.steps += 1
            return self.x
        applied = self.masses[:, None] * self.gravity[None, :]
        if forces is not None:
            applied = applied + np.asarray(forces, dtype=float).reshape(self.rest.shape)
        total = applied + self.internal_forces(self.x)
        total[self.fixed] = 0.0
        magnitude = np.sqrt(np.einsum("nd,nd->n", total, total))
        self.unbalanced = float(magnitude.max(initial=0.0))
        load = float(np.sqrt(np.einsum("nd,nd->n", applied, applied))[~self.fixed].max(initial=0))
        if load > 0:
            self._load_scale = load
        if load > 0:  # unloaded, the equilibrium is rest: the distance is the displacement
            self._moved_scale = float(np.linalg.norm(self.x - self.rest))  # the last loaded one
        self.settled = bool(
            self.unbalanced < self.settle_tolerance * self._load_scale
            or np.linalg.norm(total) < self.settle_stiffness * self._moved_scale
        )
        a = (self.dt / self.masses)[:, None]
        self.v = (self.v + a * total) / (1.0 + a * self.d)
        self.v[self.fixed] = 0.0
        self.x += self.dt * self.v
        self.steps += 1
        return self.x

    def region(self, nodes: np.ndarray, depth: int | str | None = "export") -> Region:
        """The runtime of the perturbed list of ``nodes`` (K,) int, the loaded nodes (after
        :meth:`applied`, the nodes its shares reach), up to ``depth`` layers (``"export"``:
        the runtime's own :attr:`depth`; None: every layer the springs reach): those nodes free
        (fixed nodes stay fixed), the nodes one spring or hexahedron beyond held at rest, the
        rest of the lattice left out. Same d, dt, settle criteria, backend and precision."""
        depth = self.depth if depth == "export" else depth
        if isinstance(depth, str):
            raise ValueError(f"depth: a number of layers, None or 'export', not {depth!r}")
        n, (i, j) = self.n_nodes, self.springs.T
        graph = sp.csr_matrix((np.ones(2 * len(i), bool), (np.r_[i, j], np.r_[j, i])), (n, n))
        free = np.zeros(n, dtype=bool)
        layer = np.unique(np.asarray(nodes, dtype=np.int64))
        layer = layer[~self.fixed[layer]]
        free[layer], layers = True, 0
        while len(layer) and (depth is None or layers < depth):  # the paper's layers
            reached = np.unique(graph[layer].indices)
            layer = reached[~free[reached] & ~self.fixed[reached]]
            free[layer] = True
            layers += len(layer) > 0
        springs = np.flatnonzero(free[self.springs].any(axis=1))
        cells = (
            np.flatnonzero(free[self.hexahedra].any(axis=1))
            if len(self.hexahedra)
            else np.zeros(0, int)
        )
        ends = [self.springs[springs].ravel(), self.hexahedra[cells].ravel()]
        kept = np.unique(np.concatenate([*ends, np.flatnonzero(free)]))
        local = np.full(n, -1, dtype=np.int64)
        local[kept] = np.arange(len(kept))
        runtime = Runtime(
            rest=self.rest[kept],
            masses=self.masses[kept],
            fixed=~free[kept],
            springs=local[self.springs[springs]],
            rest_lengths=self.rest_lengths[springs],
            stiffness=self.stiffness[springs],
            hexahedra=local[self.hexahedra[cells]].reshape(-1, 8),
            kappa=self.kappa[cells],
            rest_volumes=self.rest_volumes[cells],
            d=self.d,
            dt=self.dt,
            settle_tolerance=self.settle_tolerance,
            settle_stiffness=self.settle_stiffness,
            damping=self.damping,
            gravity=self.gravity,
            backend=self.backend_used,
            precision=self.precision,
            depth=None,
        )
        return Region(runtime, kept, layers)

    def run(self, forces: np.ndarray | None = None, max_steps: int = 100_000) -> int:
        """Step under constant ``forces`` until settled or ``max_steps``; the steps taken."""
        for n in range(1, max_steps + 1):
            self.step(forces)
            if self.settled:
                return n
        return max_steps


@dataclass
class Region:
    """A perturbed list as a runtime of its own (:meth:`Runtime.region`).

    Attributes:
        runtime: the list's nodes free, the ring beyond held at rest (its own numbering).
        nodes: (M,) int64 the lattice's index of each of the runtime's nodes.
        layers: the layers the list reached after the loaded one.
    """

    runtime: Runtime
    nodes: np.ndarray
    layers: int

    def forces(self, forces: np.ndarray) -> np.ndarray:
        """(M, 3) the region's share of the lattice's nodal ``forces`` (N, 3), N (a force on a
        node outside the region is dropped: it would not move the list)."""
        return np.asarray(forces).reshape(-1, 3)[self.nodes]

    def positions(self, rest: np.ndarray) -> np.ndarray:
        """(N, 3) the lattice's positions: ``rest`` (N, 3) with the region's nodes where its
        runtime has them, m."""
        x = np.array(rest, dtype=float)
        x[self.nodes] = self.runtime.x
        return x
