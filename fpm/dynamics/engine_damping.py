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
spec's dt; these are the all-at-once step's, for an engine (:func:`with_engine_damping`).
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


@dataclass(frozen=True)
class EngineDamping:
    """The all-at-once step's fastest-settling parameters.

    Attributes:
        d: nodal damping, N s/m.
        dt: time step, s.
        omega_min, omega_max: the slowest and fastest angular frequencies at rest, rad/s.
        decay: the factor every mode's error shrinks by in a step at (d, dt), as predicted for
            equal node masses (on a lattice whose surface nodes are lighter it is slower).
    """

    d: float
    dt: float
    omega_min: float
    omega_max: float
    decay: float


def rest_stiffness(rt: Runtime) -> sp.csr_matrix:
    """(3N, 3N) the stiffness K at rest of ``rt``'s model (springs k e e^T, the volume term
    (kappa / V0) g g^T per hexahedron), N/m; degrees of freedom x y z per node."""
    from ..runtime import hexahedron_volumes

    i, j = rt.springs[:, 0], rt.springs[:, 1]
    r = rt.rest[j] - rt.rest[i]
    e = r / np.linalg.norm(r, axis=1)[:, None]
    block = rt.stiffness[:, None, None] * e[:, :, None] * e[:, None, :]  # (S, 3, 3)
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((3 * p[:, None, None] + a).ravel())
        cols.append((3 * q[:, None, None] + b).ravel())
        vals.append((sign * block).ravel())
    if len(rt.hexahedra):
        _, grad = hexahedron_volumes(rt.rest, rt.hexahedra)  # (H, 8, 3)
        g = grad.reshape(len(grad), 24)
        dofs = (3 * rt.hexahedra[:, :, None] + np.arange(3)).reshape(-1, 24)
        weight = (rt.kappa / rt.rest_volumes)[:, None, None]
        rows.append(np.repeat(dofs, 24, axis=1).ravel())
        cols.append(np.tile(dofs, (1, 24)).ravel())
        vals.append((weight * g[:, :, None] * g[:, None, :]).ravel())
    n = 3 * rt.n_nodes
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), (n, n)
    )


def engine_damping(rt: Runtime, margin: float = MARGIN) -> EngineDamping:
    """The d and dt of the module docstring for ``rt``'s lattice (its fixed nodes held)."""
    free = np.repeat(~rt.fixed, 3)
    k = rest_stiffness(rt)[free][:, free].tocsc()
    m = np.repeat(rt.masses, 3)[free]
    mass = sp.diags(m).tocsc()
    top = float(spla.eigsh(k, k=1, M=mass, which="LA", return_eigenvectors=False)[0])
    low, phi = spla.eigsh(k, k=1, M=mass, sigma=0.0, which="LM")
    omega_min, omega_max = float(np.sqrt(low[0])), margin * float(np.sqrt(top))
    v = phi[:, 0]
    m_eff = float(v @ (m * v) / (v @ v))
    dt = 2.0 / (omega_max - omega_min)
    q = (omega_max + omega_min) / (omega_max - omega_min)
    return EngineDamping(
        d=(q * q - 1.0) * m_eff / dt,
        dt=dt,
        omega_min=omega_min,
        omega_max=omega_max,
        decay=1.0 / q,
    )


def with_engine_damping(rt: Runtime) -> tuple[Runtime, EngineDamping]:
    """A copy of ``rt`` (same backend and precision) stepping at :func:`engine_damping`'s d and
    dt, with them."""
    found = engine_damping(rt)
    return dataclasses.replace(rt, d=found.d, dt=found.dt), found
