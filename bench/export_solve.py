"""An independent static solve of the JSON export (the check on organ-sized lattices).

From the exported model alone (its nodes, springs, hexahedra with their volume stiffness and
rest volumes, fixed nodes), written here from the export's documented energy and not from fpm's
code: the static equilibrium of the export's energy (springs ``k/2 (|r| - l)^2``, cells
``kappa/2 (V - V0)^2 / V0`` with V the trilinear hexahedron's volume by 2x2x2 Gauss quadrature
of det J, exact for it), the fixed nodes and those beyond the perturbed list held: the model's
stiffness at rest (springs ``k e e^T``, cells ``(kappa / V0) g g^T``, ``g = dV/dx``), assembled
sparse, then Newton steps on its energy (a positive tangent: the springs' geometric stiffness
where stretched, the cells' Gauss-Newton term) with a line search. The loads are the user's
(the export's load cases, or any other nodal forces).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

CORNERS = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float,
)  # fmt: skip
"""The export's corner order (``hexahedra``: VTK's), in reference coordinates."""


FLOOR = 1e-6
"""The unbalanced force's share of the applied one under which :func:`solve` also stops once
Newton stalls (:data:`STALL` steps without halving it): its round-off floor, which on a large
lattice under a small load can lie above the tolerance asked."""
STALL = 20


def volume_gradients(corners: np.ndarray) -> np.ndarray:
    """(C, 8, 3) dV/dx of trilinear hexahedra with corners (C, 8, 3), m^2: at each of the
    2x2x2 Gauss points, d det J / d x_n = cof(J) dN_n (dN_n the shape function's gradient in
    reference coordinates, J = sum_n x_n dN_n^T / 8 ...), summed."""
    g = 1 / np.sqrt(3)
    out = np.zeros_like(corners)
    for r in (-g, g):
        for s in (-g, g):
            for t in (-g, g):
                a, b, c = CORNERS.T
                dn = (
                    np.stack(
                        [
                            a * (1 + s * b) * (1 + t * c),
                            (1 + r * a) * b * (1 + t * c),
                            (1 + r * a) * (1 + s * b) * c,
                        ],
                        axis=1,
                    )
                    / 8
                )  # fmt: skip  (8, 3): dN_n / d(r, s, t)
                jac = np.einsum("cni,nj->cij", corners, dn)  # (C, 3, 3)
                cof = np.linalg.det(jac)[:, None, None] * np.linalg.inv(jac).transpose(0, 2, 1)
                out += np.einsum("cij,nj->cni", cof, dn)
    return out


def volumes(corners: np.ndarray) -> np.ndarray:
    """(C,) volumes of trilinear hexahedra with corners (C, 8, 3), m^3: 2x2x2 Gauss quadrature
    of det J (exact for them)."""
    g = 1 / np.sqrt(3)
    a, b, c = CORNERS.T
    out = np.zeros(len(corners))
    for r in (-g, g):
        for s in (-g, g):
            for t in (-g, g):
                dn = np.stack(
                    [a * (1 + s * b) * (1 + t * c), (1 + r * a) * b * (1 + t * c),
                     (1 + r * a) * (1 + s * b) * c], axis=1,
                ) / 8  # fmt: skip
                out += np.linalg.det(np.einsum("cni,nj->cij", corners, dn))
    return out


def internal_forces(model: dict[str, Any], u: np.ndarray) -> np.ndarray:
    """(N, 3) the exported model's forces on its nodes displaced by ``u`` (N, 3) m, N: springs
    ``k (|r| - l) r / |r|`` and cells ``-kappa (V - V0) / V0 dV/dx`` (the export's energy)."""
    x = np.asarray(model["nodes"], dtype=float) + u
    out = np.zeros_like(x)
    springs = np.asarray(model["springs"], dtype=float)
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    r = x[j] - x[i]
    length = np.linalg.norm(r, axis=1)
    pull = (springs[:, 3] * (length - springs[:, 2]) / length)[:, None] * r
    np.add.at(out, i, pull)
    np.add.at(out, j, -pull)
    if model.get("volume_stiffness") is not None:
        hexa = np.asarray(model["hexahedra"], dtype=int)
        kappa = np.asarray(model["volume_stiffness"], dtype=float)
        v0 = np.asarray(model["rest_volumes"], dtype=float)
        pressure = kappa * (volumes(x[hexa]) - v0) / v0
        np.add.at(out, hexa, -pressure[:, None, None] * volume_gradients(x[hexa]))
    return out


def energy(model: dict[str, Any], u: np.ndarray) -> float:
    """The exported model's stored energy at displacements ``u`` (N, 3) m, J: springs
    ``k/2 (|r| - l)^2``, cells ``kappa/2 (V - V0)^2 / V0``."""
    x = np.asarray(model["nodes"], dtype=float) + u
    springs = np.asarray(model["springs"], dtype=float)
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    stretch = np.linalg.norm(x[j] - x[i], axis=1) - springs[:, 2]
    total = float(0.5 * (springs[:, 3] * stretch**2).sum())
    if model.get("volume_stiffness") is not None:
        hexa = np.asarray(model["hexahedra"], dtype=int)
        kappa = np.asarray(model["volume_stiffness"], dtype=float)
        v0 = np.asarray(model["rest_volumes"], dtype=float)
        total += float(0.5 * (kappa * (volumes(x[hexa]) - v0) ** 2 / v0).sum())
    return total


def stiffness(model: dict[str, Any], u: np.ndarray | None = None) -> sp.csr_matrix:
    """(3N, 3N) the exported model's stiffness, N/m: at rest, or at displacements ``u``
    (N, 3) m a tangent that is positive semi-definite (springs ``k (e e^T + max(1 - l/|r|, 0)
    (I - e e^T))``, cells ``(kappa / V0) g g^T`` without the pressure's curvature of V)."""
    x = np.asarray(model["nodes"], dtype=float) + (0.0 if u is None else u)
    n = len(x)
    springs = np.asarray(model["springs"], dtype=float)
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    e = x[j] - x[i]
    length = np.linalg.norm(e, axis=1)
    e /= length[:, None]
    outer = np.einsum("sa,sb->sab", e, e)
    blocks = springs[:, 3, None, None] * outer
    if u is not None:  # the springs' geometric stiffness where they are stretched
        slack = np.maximum(1 - springs[:, 2] / length, 0.0)[:, None, None]
        blocks += springs[:, 3, None, None] * slack * (np.eye(3) - outer)
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rr = 3 * p[:, None, None] + np.arange(3)[None, :, None]
        cc = 3 * q[:, None, None] + np.arange(3)[None, None, :]
        rows.append(np.broadcast_to(rr, blocks.shape).ravel())
        cols.append(np.broadcast_to(cc, blocks.shape).ravel())
        vals.append((sign * blocks).ravel())
    if model.get("volume_stiffness") is not None:
        hexa = np.asarray(model["hexahedra"], dtype=int)
        kappa = np.asarray(model["volume_stiffness"], dtype=float)
        v0 = np.asarray(model["rest_volumes"], dtype=float)
        grad = volume_gradients(x[hexa]).reshape(len(hexa), 24)
        dofs = (3 * hexa[:, :, None] + np.arange(3)).reshape(len(hexa), 24)
        local = (kappa / v0)[:, None, None] * np.einsum("ca,cb->cab", grad, grad)
        rows.append(np.broadcast_to(dofs[:, :, None], local.shape).ravel())
        cols.append(np.broadcast_to(dofs[:, None, :], local.shape).ravel())
        vals.append(local.ravel())
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n)
    )


def layers(model: dict[str, Any], loaded: np.ndarray, depth: int) -> list[np.ndarray]:
    """The perturbed list of nodal forces on ``loaded`` nodes: layer 0 the loaded nodes, layer
    i + 1 the nodes a spring joins to layer i not in an earlier one and not fixed (fixed nodes
    pass no force on; breadth-first over the springs), ``depth`` layers after the first: the
    export's ``perturbed_layers`` for its own load cases."""
    springs = np.asarray(model["springs"], dtype=float)
    i, j = springs[:, 0].astype(int), springs[:, 1].astype(int)
    n = len(model["nodes"])
    graph = sp.csr_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
    seen = np.zeros(n, dtype=bool)
    seen[np.asarray(model["fixed"], dtype=int)] = True  # fixed nodes pass no force on
    loaded = np.unique(loaded[~seen[loaded]])
    seen[loaded] = True
    out = [loaded]
    for _ in range(depth):
        reached = np.flatnonzero((graph @ np.isin(np.arange(n), out[-1])) > 0)
        new = reached[~seen[reached]]
        if not len(new):
            break
        seen[new] = True
        out.append(np.sort(new))
    return out


def solve(
    model: dict[str, Any],
    forces: np.ndarray,
    depth: int | None = None,
    *,
    nonlinear: bool = True,
    tolerance: float = 1e-7,
) -> np.ndarray:
    """(N, 3) displacements, m, of the exported model under nodal ``forces`` (N, 3) N, its
    fixed nodes held, and with ``depth`` (layers) the nodes beyond its perturbed list
    (:func:`layers`) held at rest too: the static equilibrium of the export's energy
    (``nonlinear``: Newton steps on it, each with a backtracking line search, until the
    unbalanced force is below ``tolerance`` times the applied one, or below :data:`FLOOR`
    times it where Newton stalls), or the model linearised at rest.

    Raises:
        ArithmeticError: no equilibrium within 200 Newton steps, or a singular stiffness."""
    k = stiffness(model)
    free = np.ones(len(forces), dtype=bool)
    if depth is not None:
        free[:] = False
        free[np.concatenate(layers(model, np.flatnonzero(np.abs(forces).sum(axis=1)), depth))] = 1
    free[np.asarray(model["fixed"], dtype=int)] = False
    dofs = np.flatnonzero(np.repeat(free, 3))
    u = np.zeros(forces.size)
    if not nonlinear:
        u[dofs] = _lu_solve(k[dofs][:, dofs].tocsc(), forces.ravel()[dofs])
        return u.reshape(-1, 3)
    size = np.linalg.norm(forces.ravel()[dofs])

    def total(v: np.ndarray) -> float:  # the potential energy, J
        return energy(model, v.reshape(-1, 3)) - float(forces.ravel() @ v)

    # Newton on the potential energy from rest, with a positive tangent and a backtracking
    # line search (a soft organ's loads carry the linear solution far past equilibrium)
    history: list[float] = []
    for _ in range(200):
        residual = (forces + internal_forces(model, u.reshape(-1, 3))).ravel()[dofs]
        history.append(float(np.linalg.norm(residual)))
        if history[-1] <= tolerance * size:
            return u.reshape(-1, 3)
        stalled = len(history) > STALL and history[-1] > 0.5 * min(history[-STALL - 1 : -1])
        if stalled and history[-1] <= FLOOR * size:  # the round-off floor, not a failure
            return u.reshape(-1, 3)
        tangent = stiffness(model, u.reshape(-1, 3))[dofs][:, dofs].tocsc()
        step = np.zeros_like(u)
        step[dofs] = _lu_solve(tangent, residual)
        here, slope, t = total(u), -float(residual @ step[dofs]), 1.0
        while t > 1e-8 and not total(u + t * step) <= here + 1e-4 * t * slope:
            t /= 2
        if t <= 1e-8:  # the energy no longer resolves the step: the full one, if it helps
            t = 1.0
        u += t * step
    raise ArithmeticError("the export's equilibrium did not converge in 200 Newton steps")


def _lu_solve(a: sp.csc_matrix, b: np.ndarray) -> np.ndarray:
    """a x = b for a symmetric positive definite ``a`` by sparse LU in SuperLU's symmetric mode
    (minimum degree on a + a^T, diagonal pivots): on a 3-D lattice about 2.4 times as fast as
    its default column ordering."""
    try:
        lu = spla.splu(
            a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
    except RuntimeError as error:  # "Factor is exactly singular"
        raise ArithmeticError(f"the export's stiffness is singular: {error}") from None
    return lu.solve(b)


def relative(u: np.ndarray, reference: np.ndarray) -> float:
    """Relative discrepancy, %: the sum of nodal distances over the reference's (paper Eq. 2
    over its own size)."""
    return float(
        100 * np.linalg.norm(u - reference, axis=1).sum() / np.linalg.norm(reference, axis=1).sum()
    )
