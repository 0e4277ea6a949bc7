"""The C step's arithmetic in numba, for a machine without a C compiler (one thread).

The same per-node rows as ``fpm_step.c`` (each spring at both ends, in spring index order; the
hexahedra's corner forces summed per node in slot order), so it is the NumPy recipe's arithmetic
as the C step is.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from ..runtime import Runtime

COEFF = np.array(
    [[-1, 1, 1, -1, -1, 1, 1, -1], [-1, -1, 1, 1, -1, -1, 1, 1], [-1, -1, -1, -1, 1, 1, 1, 1],
     [1, -1, 1, -1, 1, -1, 1, -1], [1, -1, -1, 1, -1, 1, 1, -1], [1, 1, -1, -1, -1, -1, 1, 1]],
    dtype=np.float64,
)  # fmt: skip
"""(6, 8) 8 C_kn (fpm.runtime.COEFFICIENTS times 8)."""
TRIPLE = np.array([[0, 1, 2], [0, 3, 4], [3, 1, 5], [4, 5, 2]], dtype=np.int64)
TRIPLE_W = np.array([8.0, 8.0 / 3.0, 8.0 / 3.0, 8.0 / 3.0])


def rows(n: int, springs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-node rows of the springs: (N + 1,) offsets, (2 S,) the other end and the spring's
    index, each row in spring index order."""
    s = len(springs)
    node = np.concatenate([springs[:, 0], springs[:, 1]])
    other = np.concatenate([springs[:, 1], springs[:, 0]])
    index = np.tile(np.arange(s), 2)
    order = np.lexsort((index, node))
    offsets = np.concatenate([[0], np.cumsum(np.bincount(node, minlength=n))])
    return offsets.astype(np.int64), other[order].astype(np.int64), index[order]


@njit(cache=True, nogil=True)
def _hex_forces(x, hexahedra, kappa, volume0, fc):  # pragma: no cover - compiled
    p = np.empty((8, 3))
    a = np.empty((6, 3))
    ga = np.empty((6, 3))
    g = np.empty((8, 3))
    for c in range(len(hexahedra)):
        for n in range(8):
            for d in range(3):
                p[n, d] = x[hexahedra[c, n], d]
        for k in range(6):
            for d in range(3):
                s = 0.0
                for n in range(8):
                    s += COEFF[k, n] * p[n, d]
                a[k, d] = s / 8
        ga[:] = 0.0
        volume = 0.0
        for t in range(4):
            P, Q, R = TRIPLE[t, 0], TRIPLE[t, 1], TRIPLE[t, 2]
            w = TRIPLE_W[t]
            qr0 = a[Q, 1] * a[R, 2] - a[Q, 2] * a[R, 1]
            qr1 = a[Q, 2] * a[R, 0] - a[Q, 0] * a[R, 2]
            qr2 = a[Q, 0] * a[R, 1] - a[Q, 1] * a[R, 0]
            rp0 = a[R, 1] * a[P, 2] - a[R, 2] * a[P, 1]
            rp1 = a[R, 2] * a[P, 0] - a[R, 0] * a[P, 2]
            rp2 = a[R, 0] * a[P, 1] - a[R, 1] * a[P, 0]
            pq0 = a[P, 1] * a[Q, 2] - a[P, 2] * a[Q, 1]
            pq1 = a[P, 2] * a[Q, 0] - a[P, 0] * a[Q, 2]
            pq2 = a[P, 0] * a[Q, 1] - a[P, 1] * a[Q, 0]
            volume += w * (a[P, 0] * qr0 + a[P, 1] * qr1 + a[P, 2] * qr2)
            ga[P, 0] += w * qr0
            ga[P, 1] += w * qr1
            ga[P, 2] += w * qr2
            ga[Q, 0] += w * rp0
            ga[Q, 1] += w * rp1
            ga[Q, 2] += w * rp2
            ga[R, 0] += w * pq0
            ga[R, 1] += w * pq1
            ga[R, 2] += w * pq2
        for n in range(8):
            for d in range(3):
                s = 0.0
                for k in range(6):
                    s += COEFF[k, n] * ga[k, d]
                g[n, d] = s / 8
        pressure = kappa[c] * (volume - volume0[c]) / volume0[c]
        for n in range(8):
            for d in range(3):
                fc[8 * c + n, d] = -pressure * g[n, d]


@njit(cache=True, nogil=True, inline="always")
def _node_force(x, i, row, nbr, length0, k, corner_row, corner_slot, fc, has_volume, f):
    xi, yi, zi = x[i, 0], x[i, 1], x[i, 2]
    sx = sy = sz = 0.0
    for e in range(row[i], row[i + 1]):
        j = nbr[e]
        rx, ry, rz = x[j, 0] - xi, x[j, 1] - yi, x[j, 2] - zi
        length = np.sqrt(rx * rx + ry * ry + rz * rz)
        c = k[e] * (length - length0[e]) / length
        sx += c * rx
        sy += c * ry
        sz += c * rz
    if has_volume:
        cx = cy = cz = 0.0
        for e in range(corner_row[i], corner_row[i + 1]):
            q = corner_slot[e]
            cx += fc[q, 0]
            cy += fc[q, 1]
            cz += fc[q, 2]
        sx += cx
        sy += cy
        sz += cz
    f[0], f[1], f[2] = sx, sy, sz


@njit(cache=True, nogil=True)
def _internal(x, row, nbr, length0, k, hexahedra, kappa, volume0, corner_row, corner_slot, fc):
    has_volume = len(hexahedra) > 0
    _hex_forces(x, hexahedra, kappa, volume0, fc)
    out = np.empty_like(x)
    f = np.empty(3)
    for i in range(len(x)):
        _node_force(x, i, row, nbr, length0, k, corner_row, corner_slot, fc, has_volume, f)
        out[i] = f
    return out


@njit(cache=True, nogil=True)
def _step(x, x_next, v, forces, has_forces, rest, mg, a, denom, fixed, dt, row, nbr, length0,
          k, hexahedra, kappa, volume0, corner_row, corner_slot, fc):  # fmt: skip
    has_volume = len(hexahedra) > 0
    _hex_forces(x, hexahedra, kappa, volume0, fc)
    f = np.empty(3)
    applied = np.empty(3)
    total = np.empty(3)
    unbalanced = load = sum2 = moved2 = 0.0
    for i in range(len(x)):
        _node_force(x, i, row, nbr, length0, k, corner_row, corner_slot, fc, has_volume, f)
        for d in range(3):
            applied[d] = mg[i, d]
            if has_forces:
                applied[d] = applied[d] + forces[i, d]
            total[d] = applied[d] + f[d]
            u = x[i, d] - rest[i, d]
            moved2 += u * u
        if fixed[i]:
            for d in range(3):
                v[i, d] = 0.0
                x_next[i, d] = x[i, d]
            continue
        mag2 = total[0] * total[0] + total[1] * total[1] + total[2] * total[2]
        sum2 += mag2
        unbalanced = max(unbalanced, np.sqrt(mag2))
        pull = applied[0] * applied[0] + applied[1] * applied[1] + applied[2] * applied[2]
        load = max(load, np.sqrt(pull))
        for d in range(3):
            vn = (v[i, d] + a[i] * total[d]) / denom[i]
            v[i, d] = vn
            x_next[i, d] = x[i, d] + dt * vn
    return unbalanced, load, sum2, moved2


class NumbaStep:
    """The step of a :class:`~fpm.runtime.Runtime`'s arrays, compiled by numba."""

    name = "numba"
    dtype = np.float64

    def __init__(self, rt: Runtime) -> None:
        n = rt.n_nodes
        self.row, self.nbr, index = rows(n, rt.springs)
        self.length0 = rt.rest_lengths[index].copy()
        self.k = rt.stiffness[index].copy()
        self.hexahedra = np.ascontiguousarray(rt.hexahedra, dtype=np.int64)
        flat = self.hexahedra.ravel()
        self.corner_slot = np.argsort(flat, kind="stable").astype(np.int64)
        self.corner_row = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n))])
        self.kappa, self.volume0 = rt.kappa.astype(float), rt.rest_volumes.astype(float)
        self.fc = np.zeros((len(flat), 3))
        self.rest, self.fixed, self.dt = rt.rest, rt.fixed, float(rt.dt)
        self.mg = rt.masses[:, None] * rt.gravity[None, :]
        self.a = rt.dt / rt.masses
        self.denom = 1.0 + self.a * rt.d
        self.tolerance, self.stiffness = rt.settle_tolerance, rt.settle_stiffness
        self._none = np.zeros((1, 3))
        self.reset()

    def reset(self) -> None:
        self.load_scale = self.moved_scale = 0.0

    def internal_forces(self, x: np.ndarray) -> np.ndarray:
        return _internal(
            np.ascontiguousarray(x, dtype=float), self.row, self.nbr, self.length0, self.k,
            self.hexahedra, self.kappa, self.volume0, self.corner_row, self.corner_slot, self.fc,
        )  # fmt: skip

    def step(
        self, x: np.ndarray, x_next: np.ndarray, v: np.ndarray, forces: np.ndarray | None
    ) -> tuple[float, bool]:
        f = self._none if forces is None else forces
        unbalanced, load, sum2, moved2 = _step(
            x, x_next, v, f, forces is not None, self.rest, self.mg, self.a, self.denom,
            self.fixed, self.dt, self.row, self.nbr, self.length0, self.k, self.hexahedra,
            self.kappa, self.volume0, self.corner_row, self.corner_slot, self.fc,
        )  # fmt: skip
        if load > 0:
            self.load_scale, self.moved_scale = load, float(np.sqrt(moved2))
        settled = bool(
            unbalanced < self.tolerance * self.load_scale
            or np.sqrt(sum2) < self.stiffness * self.moved_scale
        )
        return float(unbalanced), settled
