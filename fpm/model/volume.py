"""The volume term: a per-cell resistance to change of volume (docs/physics.md, *The volume term*).

Central springs alone obey the Cauchy relation (C12 = C44, Poisson's ratio 1/4). Each lattice
cell c (an 8-node hexahedron) therefore carries an energy

    W_c = 1/2 kappa_c (V_c - V0_c)^2 / V0_c,

V_c the volume of the trilinear hexahedron spanned by its 8 corners, V0_c its rest volume and
kappa_c (Pa) its volume stiffness; the force on corner n is
``f_n = -kappa_c (V_c - V0_c) / V0_c * dV_c/dx_n``. Its continuum limit adds kappa to C11 and
C12 and nothing to C44, so springs plus kappa can be any isotropic solid with nu >= 1/4.

The volume in closed form. Write the trilinear map x(r, s, t) = sum_n N_n x_n (paper Eq. 3) as
``a0 + a1 r + a2 s + a3 t + a4 rs + a5 rt + a6 st + a7 rst`` with
``a_k = sum_n C_kn x_n`` (:data:`COEFFICIENTS`, the corner's natural coordinates and their
products over 8). Integrating det(dx/dr, dx/ds, dx/dt) over [-1, 1]^3, every term with an odd
power vanishes, and what remains is

    V = 8 [a1, a2, a3] + 8/3 ([a1, a4, a5] + [a4, a2, a6] + [a5, a6, a3]),

[a, b, c] = a . (b x c); a0 and a7 drop out. V is linear in each corner's position (its
gradient with respect to x_n does not depend on x_n), which the tests check with finite
differences. The functions here are compiled (numba) and work on one cell's (6, 3) array of
a1..a6 (``a``); the dynamic kernel (:mod:`fpm.dynamics.voigt`) and the static solver's cell
kernels (:mod:`fpm.dynamics.cell_terms`) call them per cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .hexahedron import NATURAL

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
"""(6, 8) C_kn: a_k = sum_n C_kn x_n for k = 1..6 (r, s, t, rs, rt, st)."""

_TRIPLES = ((0, 1, 2, 8.0), (0, 3, 4, 8.0 / 3.0), (3, 1, 5, 8.0 / 3.0), (4, 5, 2, 8.0 / 3.0))
"""The volume as weighted triple products of a1..a6 (0-based): (p, q, r, weight)."""


@dataclass(frozen=True)
class Cells:
    """The lattice cells that carry the volume term, as arrays.

    Attributes:
        corners: (C, 8) int64 node indices of each cell (:mod:`fpm.model.hexahedron` order).
        rest: (C, 6, 3) a1..a6 of each cell at rest, m.
        volume: (C,) rest volumes V0, m^3 (> 0).
    """

    corners: np.ndarray
    rest: np.ndarray
    volume: np.ndarray

    @classmethod
    def from_hexahedra(cls, nodes: np.ndarray, hexahedra: np.ndarray) -> Cells:
        """Cells of (H, 8) ``hexahedra`` over rest ``nodes`` (N, 3)."""
        corners = np.ascontiguousarray(hexahedra, dtype=np.int64)
        rest = np.ascontiguousarray(np.einsum("kn,cnd->ckd", COEFFICIENTS, nodes[corners]))
        volume = np.array([volume_of(a) for a in rest]) if len(rest) else np.zeros(0)
        return cls(corners, rest, volume)

    def subset(self, which: np.ndarray) -> Cells:
        """The cells ``which`` (indices or a mask)."""
        return Cells(self.corners[which], self.rest[which], self.volume[which])


@njit(cache=True, nogil=True, inline="always")
def _triple(a: np.ndarray, p: int, b: np.ndarray, q: int, c: np.ndarray, r: int) -> float:
    """[a_p, b_q, c_r] = a_p . (b_q x c_r) for rows of (6, 3) arrays."""
    x0 = b[q, 1] * c[r, 2] - b[q, 2] * c[r, 1]
    x1 = b[q, 2] * c[r, 0] - b[q, 0] * c[r, 2]
    x2 = b[q, 0] * c[r, 1] - b[q, 1] * c[r, 0]
    return a[p, 0] * x0 + a[p, 1] * x1 + a[p, 2] * x2


@njit(cache=True, nogil=True)
def volume_of(a: np.ndarray) -> float:
    """V, m^3, of the cell whose a1..a6 are ``a`` (6, 3)."""
    return 8.0 * _triple(a, 0, a, 1, a, 2) + (8.0 / 3.0) * (
        _triple(a, 0, a, 3, a, 4) + _triple(a, 3, a, 1, a, 5) + _triple(a, 4, a, 5, a, 2)
    )


@njit(cache=True, nogil=True)
def volume_change(a: np.ndarray, da: np.ndarray) -> float:
    """V(a + da) - V(a), m^3, without the cancellation of subtracting two volumes: each triple
    product [a+da, b+db, c+dc] - [a, b, c] expanded into its seven terms with a d-factor."""
    total = 0.0
    for t in range(4):
        p, q, r, w = _TRIPLES[t]
        s = (
            _triple(da, p, a, q, a, r)
            + _triple(a, p, da, q, a, r)
            + _triple(a, p, a, q, da, r)
            + _triple(da, p, da, q, a, r)
            + _triple(da, p, a, q, da, r)
            + _triple(a, p, da, q, da, r)
            + _triple(da, p, da, q, da, r)
        )
        total += w * s
    return total


@njit(cache=True, nogil=True, inline="always")
def _cross_add(out: np.ndarray, k: int, w: float, b: np.ndarray, q: int, c: np.ndarray, r: int):
    """out[k] += w * (b_q x c_r)."""
    out[k, 0] += w * (b[q, 1] * c[r, 2] - b[q, 2] * c[r, 1])
    out[k, 1] += w * (b[q, 2] * c[r, 0] - b[q, 0] * c[r, 2])
    out[k, 2] += w * (b[q, 0] * c[r, 1] - b[q, 1] * c[r, 0])


@njit(cache=True, nogil=True)
def coefficient_gradient(a: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` (6, 3) with dV/da_k, m^2: for each weighted [a_p, a_q, a_r],
    d/da_p = a_q x a_r, d/da_q = a_r x a_p, d/da_r = a_p x a_q."""
    out[:] = 0.0
    for t in range(4):
        p, q, r, w = _TRIPLES[t]
        _cross_add(out, p, w, a, q, a, r)
        _cross_add(out, q, w, a, r, a, p)
        _cross_add(out, r, w, a, p, a, q)


@njit(cache=True, nogil=True)
def corner_gradient(coefficient_grad: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` (8, 3) with dV/dx_n = sum_k C_kn dV/da_k, m^2."""
    for n in range(8):
        for d in range(3):
            value = 0.0
            for k in range(6):
                value += COEFFICIENTS[k, n] * coefficient_grad[k, d]
            out[n, d] = value


@njit(cache=True, nogil=True)
def coefficient_hessian(a: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` (6, 6, 3, 3) with d^2 V / da_k da_l (block (k, l) is the 3x3 matrix of
    the bilinear form): for [a_p, a_q, a_r], the (p, q) block is -[a_r]_x (and its transpose at
    (q, p)), cyclically; the diagonal blocks are zero."""
    out[:] = 0.0
    for t in range(4):
        p, q, r, w = _TRIPLES[t]
        for i0, i1, i2 in ((p, q, r), (q, r, p), (r, p, q)):
            c0, c1, c2 = a[i2, 0], a[i2, 1], a[i2, 2]
            # -[c]_x = [[0, c2, -c1], [-c2, 0, c0], [c1, -c0, 0]]
            out[i0, i1, 0, 1] += w * c2
            out[i0, i1, 0, 2] -= w * c1
            out[i0, i1, 1, 0] -= w * c2
            out[i0, i1, 1, 2] += w * c0
            out[i0, i1, 2, 0] += w * c1
            out[i0, i1, 2, 1] -= w * c0
            for x in range(3):
                for y in range(3):
                    out[i1, i0, y, x] = out[i0, i1, x, y]


def cell_volumes(cells: Cells, displacements: np.ndarray) -> np.ndarray:
    """(C,) volume changes V - V0, m^3, at nodal ``displacements`` (N, 3), m (NumPy; for
    checks and exports, not hot loops)."""
    da = np.einsum("kn,cnd->ckd", COEFFICIENTS, displacements[cells.corners])
    return np.array([volume_change(a, d) for a, d in zip(cells.rest, da, strict=True)])


def volume_energy(cells: Cells, kappa: np.ndarray, displacements: np.ndarray) -> float:
    """sum_c 1/2 kappa_c (V_c - V0_c)^2 / V0_c, J, at ``displacements`` (N, 3), m."""
    change = cell_volumes(cells, displacements)
    return float(0.5 * np.sum(kappa * change * change / cells.volume))


def volume_forces(cells: Cells, kappa: np.ndarray, displacements: np.ndarray) -> np.ndarray:
    """(N, 3) nodal forces of the volume term, N: -kappa_c (V_c - V0_c) / V0_c dV_c/dx_n."""
    forces = np.zeros_like(displacements)
    da = np.einsum("kn,cnd->ckd", COEFFICIENTS, displacements[cells.corners])
    grad_a, grad_x = np.empty((6, 3)), np.empty((8, 3))
    for c in range(len(cells.volume)):
        a = cells.rest[c] + da[c]
        pressure = kappa[c] * volume_change(cells.rest[c], da[c]) / cells.volume[c]
        coefficient_gradient(a, grad_a)
        corner_gradient(grad_a, grad_x)
        np.add.at(forces, cells.corners[c], -pressure * grad_x)
    return forces
