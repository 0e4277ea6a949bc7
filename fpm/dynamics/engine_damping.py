"""The d and dt with which the all-at-once step (:mod:`fpm.runtime`, the step engines run)
settles fastest and stays stable, from the slowest and fastest modes of M^-1 K at rest.

One mode of M^-1 K with eigenvalue w^2 under the step (u, dt v) <- A (u, dt v), s = (w dt)^2,
c = dt d / m (fpm.dynamics.stability, steps 1 and 2), has the characteristic polynomial
``l^2 - l (2 + c - s) / (1 + c) + 1 / (1 + c)``: while its roots are complex they have modulus
``1 / q``, q = sqrt(1 + c), whatever w; they are complex for ``q - 1 <= w dt <= q + 1``. Every
mode then decays by the same factor 1/q a step, and the fastest such step puts the slowest mode
at the lower end and the fastest at the upper one:

    w_min dt = q - 1,   w_max dt = q + 1   =>   dt = 2 / (w_max - w_min),
    q = (w_max + w_min) / (w_max - w_min),   d = (q^2 - 1) m / dt,

each mode's error shrinking by (w_max - w_min) / (w_max + w_min) a step (about 1 - 2 / kappa,
kappa = w_max / w_min). m is the slowest mode's effective node mass, phi^T M phi / phi^T phi
(d acts per node, so a mode feels d over its nodes' mass). A margin on w_max (:data:`MARGIN`)
keeps the fastest mode inside, since masses differ between nodes.

The calibration's ``d`` is the fastest-settling damping of its own node-by-node kernel at the
spec's dt; these are the all-at-once step's, for an engine (:func:`with_engine_damping`). The
JSON export carries them as ``parameters.engine`` (:meth:`EngineDamping.as_export`), computed
when it is written (:func:`fpm.io.export.engine_parameters`), and :mod:`fpm.runtime` steps at
them by default.

The two modes: w_max by Lanczos on M^-1/2 K M^-1/2 (ARPACK, largest); w_min exactly by
shift-invert (a sparse LU of K) up to :data:`DIRECT_UP_TO` unknowns, above by LOBPCG
preconditioned by a multigrid V-cycle of K (:func:`fpm.dynamics.eigen.lowest_modes`, the same
hierarchy as the static solver's), whose w_min is an upper bound.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

if TYPE_CHECKING:
    from ..runtime import Runtime

MARGIN = 1.05
"""w_max is taken this much faster than found."""
DIRECT_UP_TO = 5_000
"""Free unknowns up to which w_min comes from shift-invert on a sparse LU (exact); above, from
LOBPCG with a multigrid preconditioner (the linear solver's own crossover,
:data:`fpm.fem.linear_solver.AMG_FROM_UNKNOWNS`)."""


@dataclass(frozen=True)
class EngineDamping:
    """The all-at-once step's fastest-settling parameters.

    Attributes:
        d: nodal damping, N s/m.
        dt: time step, s.
        omega_min, omega_max: the slowest and fastest angular frequencies at rest, rad/s
            (omega_max with the margin).
        decay: the factor every mode's error shrinks by in a step at (d, dt), as predicted for
            equal node masses (on a lattice whose surface nodes are lighter it is slower).
        mode_mass: the slowest mode's effective node mass m, kg (d = (q^2 - 1) m / dt).
        margin: the factor omega_max was taken faster than found.
    """

    d: float
    dt: float
    omega_min: float
    omega_max: float
    decay: float
    mode_mass: float = float("nan")
    margin: float = MARGIN

    def as_export(self) -> dict[str, float]:
        """The JSON export's ``parameters.engine`` block (docs/reference/json-export.md)."""
        return {
            "d": self.d,
            "dt": self.dt,
            "decay_per_step": self.decay,
            "omega_min": self.omega_min,
            "omega_max": self.omega_max,
            "mode_mass": self.mode_mass,
            "margin": self.margin,
        }


@dataclass(frozen=True)
class RestLattice:
    """What :func:`engine_damping` reads of a lattice (a :class:`~fpm.runtime.Runtime` has the
    same attributes): rest positions (N, 3) m, masses (N,) kg, fixed (N,) bool, springs (S, 2),
    their stiffness (S,) N/m, hexahedra (H, 8) in NATURAL order (or (0, 8)), kappa (H,) Pa,
    rest volumes (H,) m^3."""

    rest: np.ndarray
    masses: np.ndarray
    fixed: np.ndarray
    springs: np.ndarray
    stiffness: np.ndarray
    hexahedra: np.ndarray
    kappa: np.ndarray
    rest_volumes: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.rest)


def rest_stiffness(rt: Runtime | RestLattice) -> sp.csr_matrix:
    """(3N, 3N) the stiffness K at rest of ``rt``'s model (springs k e e^T, the volume term
    (kappa / V0) g g^T per hexahedron), N/m; degrees of freedom x y z per node. Assembled as
    B^T diag(k) B + G^T diag(kappa / V0) G, B's row s the spring's unit vector (-e at i, e at
    j), G's row c the hexahedron's dV/dx at rest."""
    from ..runtime import hexahedron_volumes

    n = 3 * rt.n_nodes
    i, j = rt.springs[:, 0], rt.springs[:, 1]
    r = rt.rest[j] - rt.rest[i]
    e = r / np.linalg.norm(r, axis=1)[:, None]
    s = len(i)
    columns = np.concatenate([3 * i[:, None] + np.arange(3), 3 * j[:, None] + np.arange(3)], 1)
    b = sp.csr_matrix(
        (np.concatenate([-e, e], axis=1).ravel(), columns.ravel(), np.arange(0, 6 * s + 1, 6)),
        (s, n),
    )
    k = b.T @ sp.diags(np.asarray(rt.stiffness, dtype=float)) @ b
    if len(rt.hexahedra) and len(rt.kappa):
        _, grad = hexahedron_volumes(rt.rest, rt.hexahedra)  # (H, 8, 3)
        h = len(grad)
        dofs = (3 * rt.hexahedra[:, :, None] + np.arange(3)).reshape(-1, 24)
        g = sp.csr_matrix(
            (grad.reshape(h, 24).ravel(), dofs.ravel(), np.arange(0, 24 * h + 1, 24)), (h, n)
        )
        k = k + g.T @ sp.diags(rt.kappa / rt.rest_volumes) @ g
    return sp.csr_matrix(k)


def _slowest(k: sp.csr_matrix, masses: np.ndarray, rest: np.ndarray) -> tuple[float, np.ndarray]:
    """(w_min^2, its mode (3M,)) of K phi = w^2 M phi, ``masses`` (M,) per free node at
    ``rest`` (M, 3) (module docstring: exact up to :data:`DIRECT_UP_TO` unknowns)."""
    m = np.repeat(masses, 3)
    if k.shape[0] > DIRECT_UP_TO:
        from ..fem.linear_solver import amg_hierarchy, rigid_body_modes
        from .eigen import lowest_modes

        bsr = k.tobsr(blocksize=(3, 3))
        hierarchy = amg_hierarchy(bsr, rigid_body_modes(rest))
        if len(hierarchy.levels) > 1:
            modes = lowest_modes(bsr, masses, 1, hierarchy=hierarchy)
            if len(modes.w2) and modes.w2[0] > 0:
                return float(modes.w2[0]), modes.shapes[:, 0]
    start = np.random.default_rng(0).standard_normal(k.shape[0])  # ARPACK's: the same bits
    low, phi = spla.eigsh(k.tocsc(), k=1, M=sp.diags(m).tocsc(), sigma=0.0, which="LM", v0=start)
    return float(low[0]), phi[:, 0]


def engine_damping(rt: Runtime | RestLattice, margin: float = MARGIN) -> EngineDamping:
    """The d and dt of the module docstring for ``rt``'s lattice (its fixed nodes held)."""
    held = ~np.asarray(rt.fixed, dtype=bool)
    free = np.repeat(held, 3)
    k = rest_stiffness(rt)[free][:, free].tocsr()
    m = np.repeat(rt.masses, 3)[free]
    scale = sp.diags(1.0 / np.sqrt(m))
    start = np.random.default_rng(0).standard_normal(k.shape[0])  # the same bits every export
    top = float(
        spla.eigsh(
            scale @ k @ scale, k=1, which="LA", tol=1e-4, v0=start, return_eigenvectors=False
        )[0]
    )
    low, v = _slowest(k, np.asarray(rt.masses, dtype=float)[held], np.asarray(rt.rest)[held])
    omega_min, omega_max = float(np.sqrt(low)), margin * float(np.sqrt(top))
    m_eff = float(v @ (m * v) / (v @ v))
    dt = 2.0 / (omega_max - omega_min)
    q = (omega_max + omega_min) / (omega_max - omega_min)
    return EngineDamping(
        d=(q * q - 1.0) * m_eff / dt,
        dt=dt,
        omega_min=omega_min,
        omega_max=omega_max,
        decay=1.0 / q,
        mode_mass=m_eff,
        margin=margin,
    )


def with_engine_damping(rt: Runtime) -> tuple[Runtime, EngineDamping]:
    """A copy of ``rt`` (same backend and precision) stepping at :func:`engine_damping`'s d and
    dt, with them."""
    found = engine_damping(rt)
    return dataclasses.replace(rt, d=found.d, dt=found.dt, damping="engine"), found
