"""Neo-Hookean hexahedra, total Lagrangian: energy, nodal forces and tangent, two integrations.

``"full"`` (:class:`CompressibleNeoHookean`): strain energy per unit reference volume, Pa
(J/m^3), at the 2x2x2 Gauss points::

    W(F) = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2,    I1 = tr(F^T F),  J = det F

with the Lame constants ``mu``, ``lambda`` of E and nu
(:func:`fpm.model.spec.lame_constants`). Its first Piola-Kirchhoff stress and the derivative
of that stress (the material tangent), Pa::

    P = mu (F - F^-T) + lambda ln J F^-T
    dP_iJ/dF_kL = mu d_ik d_JL + (mu - lambda ln J) Finv_Li Finv_Jk + lambda Finv_Ji Finv_Lk

``"selective"`` (:class:`MeanDilatationNeoHookean`, the default): the decoupled neo-Hookean
solid with its volume change taken on the element's mean dilatation (Simo, Taylor and Pister
1985), the large-deformation form of the linear FEM's B-bar: per hexahedron::

    E_e = sum_g w_g mu/2 (J_g^(-2/3) I1_g - 3) + V0_e K/2 (ln Jbar_e)^2,    Jbar_e = V_e / V0_e

``K = lambda + 2 mu / 3`` the bulk modulus, ``V_e = sum_g w_g J_g`` the deformed volume (exact:
2x2x2 points integrate the trilinear element's det F), ``V0_e`` the rest volume. The
isochoric part cannot lock; the volume is held once per element, not at every Gauss point.

At F = I both tangents are the linear elements' (``"full"``: the isotropic C of
:func:`fpm.fem.elasticity.constitutive_matrix` at 2x2x2 points; ``"selective"``: B-bar), so
small loads reproduce the linear FEM of the same integration. The elements are the linear
FEM's: 8-node trilinear hexahedra (:mod:`fpm.model.hexahedron` order), 2x2x2 Gauss points,
quantities of the reference (undeformed) configuration fixed once (:func:`reference_gradients`).
Everything is vectorised over elements and Gauss points: H hexahedra, G = 8 Gauss points, 8
local nodes a, b; indices i, k spatial, J, L material axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.hexahedron import GAUSS_POINTS
from .assembly import identical_elements
from .elasticity import physical_gradients


@dataclass(frozen=True)
class ReferenceGradients:
    """The undeformed hexahedra at their Gauss points.

    Attributes:
        hexahedra: (H, 8) node indices.
        gradients: (H, G, 8, 3) dN_a/dX_J of each local node a at each Gauss point, 1/m.
        weights: (H, G) Gauss weight times det(dX/dxi), m^3 (they sum to the volume).
        laplacian: (H, 8, 8) sum over Gauss points of weight * dN_a/dX . dN_b/dX, m: the part
            of the tangent that never changes (times mu).
    """

    hexahedra: np.ndarray
    gradients: np.ndarray
    weights: np.ndarray
    laplacian: np.ndarray

    def part(self, elements: slice) -> ReferenceGradients:
        """The same for a run of the hexahedra (views, no copies)."""
        return ReferenceGradients(
            self.hexahedra[elements],
            self.gradients[elements],
            self.weights[elements],
            self.laplacian[elements],
        )


def reference_gradients(nodes: np.ndarray, hexahedra: np.ndarray) -> ReferenceGradients:
    """:class:`ReferenceGradients` of ``hexahedra`` (H, 8) on ``nodes`` (N, 3), m.

    Computed once per distinct element shape (a box has one), then copied to every element.
    The caller checks det J > 0 (:func:`fpm.fem.elasticity.min_jacobian_determinants`).
    """
    shapes, which = identical_elements(nodes[hexahedra])
    grads, dets = zip(*(physical_gradients(shapes, p) for p in GAUSS_POINTS), strict=True)
    g = np.stack(grads, axis=1)  # (U, G, 8, 3)
    w = np.stack(dets, axis=1)  # (U, G); every 2x2x2 Gauss weight is 1
    laplacian = np.einsum("ug,ugaj,ugbj->uab", w, g, g)
    return ReferenceGradients(hexahedra, g[which], w[which], laplacian[which])


@dataclass(frozen=True)
class Kinematics:
    """The deformation at the Gauss points, (H, G, ...) arrays.

    Attributes:
        displacement_gradient: (H, G, 3, 3) H_iJ = du_i/dX_J = F - I.
        inverse: (H, G, 3, 3) F^-1 (not finite where det F <= 0).
        det: (H, G) J = det F.
        log_j: (H, G) ln J, from J - 1 computed without cancellation (NaN where J <= 0).
    """

    displacement_gradient: np.ndarray
    inverse: np.ndarray
    det: np.ndarray
    log_j: np.ndarray

    def i1_minus_3(self) -> np.ndarray:
        """(H, G) I1 - 3 = 2 tr H + H:H, formed from H (no digits lost at small strain)."""
        h = self.displacement_gradient
        return 2 * np.einsum("...ii->...", h) + np.einsum("...ij,...ij->...", h, h)

    def f_minus_inverse_t(self) -> np.ndarray:
        """(H, G, 3, 3) F - F^-T = H + (F^-1 H)^T, formed from H."""
        h = self.displacement_gradient
        return h + np.swapaxes(self.inverse @ h, -1, -2)


def kinematics(ref: ReferenceGradients, u: np.ndarray) -> Kinematics:
    """:class:`Kinematics` of nodal displacements ``u`` (N, 3), m.

    Small strains lose no digits: ``J - 1 = tr H + (tr^2 H - tr H^2) / 2 + det H`` here, and
    ``F - F^-T`` and ``I1 - 3`` in :class:`Kinematics`, are formed from H, not from F - I.
    """
    grad_u = np.einsum("hai,hgaj->hgij", u[ref.hexahedra], ref.gradients, optimize=True)
    f = grad_u.copy()
    f[..., [0, 1, 2], [0, 1, 2]] += 1.0
    inverse, det = inverse_and_determinant(f)
    trace = np.einsum("...ii->...", grad_u)
    second = (trace**2 - np.einsum("...ij,...ji->...", grad_u, grad_u)) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        log_j = np.log1p(trace + second + inverse_and_determinant(grad_u)[1])
    return Kinematics(grad_u, inverse, det, log_j)


def inverse_and_determinant(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3, 3) F^-1 and (...) det F of ``f`` (..., 3, 3), by cofactors.

    Where det F = 0 the inverse is not finite; the caller checks the determinant first.
    """
    cof = np.empty_like(f)
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            cof[..., i, j] = f[..., i1, j1] * f[..., i2, j2] - f[..., i1, j2] * f[..., i2, j1]
    det = np.einsum("...j,...j->...", f[..., 0, :], cof[..., 0, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.swapaxes(cof, -1, -2) / det[..., None, None]
    return inverse, det


def first_piola(kin: Kinematics, mu: float, lam: float) -> np.ndarray:
    """(H, G, 3, 3) P = mu (F - F^-T) + lambda ln J F^-T, Pa."""
    inverse_t = np.swapaxes(kin.inverse, -1, -2)
    return mu * kin.f_minus_inverse_t() + (lam * kin.log_j)[..., None, None] * inverse_t


def strain_energy(kin: Kinematics, mu: float, lam: float) -> np.ndarray:
    """(H, G) W, J/m^3."""
    return mu / 2 * kin.i1_minus_3() - mu * kin.log_j + lam / 2 * kin.log_j**2


def internal_forces(ref: ReferenceGradients, stress: np.ndarray, n_nodes: int) -> np.ndarray:
    """(N, 3) nodal internal forces f_ai = sum_g w P_iJ dN_a/dX_J, N, of P (H, G, 3, 3), Pa."""
    per_point = np.matmul(ref.gradients, np.swapaxes(stress, -1, -2))  # (H, G, 8, 3)
    per_element = np.einsum("hg,hgai->hai", ref.weights, per_point)
    return _scatter(per_element, ref.hexahedra, n_nodes)


def element_tangents(ref: ReferenceGradients, kin: Kinematics, mu: float, lam: float) -> np.ndarray:
    """(H, 8, 8, 3, 3) blocks K[h, a, b, i, k] = d f_ai / d u_bk of each hexahedron, N/m.

    With the spatial gradients g_a = F^-T dN_a/dX, the material tangent contracted with the
    reference gradients is, per Gauss point::

        w [ mu d_ik (dN_a/dX . dN_b/dX) + (mu - lambda ln J) g_bi g_ak + lambda g_ai g_bk ]

    so the element matrix is the constant mu term (:attr:`ReferenceGradients.laplacian`) plus
    two batched products of (G, 24) matrices.

    Args:
        ref: the reference gradients.
        kin: the deformation (det F > 0 everywhere).
        mu, lam: Lame constants, Pa.
    """
    g = spatial_gradients(ref, kin)
    direct = _outer(g, g, lam * ref.weights)
    crossed = _outer(g, g, (mu - lam * kin.log_j) * ref.weights)
    return _blocks(len(ref.weights), direct, crossed, mu * ref.laplacian)


def _blocks(h: int, direct: np.ndarray, crossed: np.ndarray, diagonal: np.ndarray) -> np.ndarray:
    """(H, 8, 8, 3, 3) K[h, a, b, i, k] of three (H, ...) parts: ``direct`` (H, 24, 24) indexed
    [(a, i), (b, k)], ``crossed`` (H, 24, 24) indexed [(a, k), (b, i)], and ``diagonal``
    (H, 8, 8) times d_ik."""
    k = direct.reshape(h, 8, 3, 8, 3) + crossed.reshape(h, 8, 3, 8, 3).swapaxes(2, 4)
    k = k.transpose(0, 1, 3, 2, 4)  # (H, a, b, i, k)
    k[..., [0, 1, 2], [0, 1, 2]] += diagonal[..., None]
    return k


def _outer(x: np.ndarray, y: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(H, 24, 24) sum over Gauss points of c x_(a,i) y_(b,k), of x, y (H, G, 8, 3), c (H, G)."""
    h = len(c)
    return np.matmul(
        np.swapaxes((x * c[..., None, None]).reshape(h, 8, 24), 1, 2), y.reshape(h, 8, 24)
    )


def _scatter(per_element: np.ndarray, hexahedra: np.ndarray, n_nodes: int) -> np.ndarray:
    """(N, 3) sums of per-element nodal vectors (H, 8, 3) at their nodes."""
    index = hexahedra.ravel()
    flat = per_element.reshape(-1, 3)
    return np.stack([np.bincount(index, flat[:, i], n_nodes) for i in range(3)], axis=1)


def spatial_gradients(ref: ReferenceGradients, kin: Kinematics) -> np.ndarray:
    """(H, G, 8, 3) g_a = F^-T dN_a/dX, 1/m."""
    return np.einsum("hgji,hgaj->hgai", kin.inverse, ref.gradients, optimize=True)


@dataclass(frozen=True)
class CompressibleNeoHookean:
    """``"full"`` integration: W at every Gauss point (module docstring). mu, lam: Pa."""

    mu: float
    lam: float

    def energy(self, ref: ReferenceGradients, kin: Kinematics) -> np.ndarray:
        """(H,) strain energy of each hexahedron, J."""
        return np.einsum("hg,hg->h", ref.weights, strain_energy(kin, self.mu, self.lam))

    def forces(self, ref: ReferenceGradients, kin: Kinematics, n_nodes: int) -> np.ndarray:
        """(N, 3) internal nodal forces dE/du, N."""
        return internal_forces(ref, first_piola(kin, self.mu, self.lam), n_nodes)

    def tangents(self, ref: ReferenceGradients, kin: Kinematics) -> np.ndarray:
        """(H, 8, 8, 3, 3) element blocks d f_ai / d u_bk, N/m."""
        return element_tangents(ref, kin, self.mu, self.lam)


@dataclass(frozen=True)
class MeanDilatationNeoHookean:
    """``"selective"`` integration: isochoric energy at the Gauss points, volume energy on each
    element's mean dilatation (module docstring). mu, bulk (K): Pa."""

    mu: float
    bulk: float

    def _isochoric(self, kin: Kinematics) -> tuple[np.ndarray, np.ndarray]:
        """(H, G) J^(-2/3) and I1 - 3, from H without cancellation."""
        return np.exp(-2 / 3 * kin.log_j), kin.i1_minus_3()

    def _dilatation(self, ref: ReferenceGradients, kin: Kinematics) -> tuple[np.ndarray, ...]:
        """(H,) rest volume V0, m^3, and ln Jbar of each hexahedron."""
        v0 = ref.weights.sum(axis=1)
        with np.errstate(invalid="ignore"):
            log_jbar = np.log1p(np.einsum("hg,hg->h", ref.weights, np.expm1(kin.log_j)) / v0)
        return v0, log_jbar

    def energy(self, ref: ReferenceGradients, kin: Kinematics) -> np.ndarray:
        """(H,) strain energy of each hexahedron, J: mu/2 (J^(-2/3) I1 - 3) at the Gauss points,
        with J^(-2/3) I1 - 3 = J^(-2/3) (I1 - 3) + 3 (J^(-2/3) - 1), plus V0 K/2 (ln Jbar)^2."""
        a, i1_minus_3 = self._isochoric(kin)
        w_iso = self.mu / 2 * (a * i1_minus_3 + 3 * np.expm1(-2 / 3 * kin.log_j))
        v0, log_jbar = self._dilatation(ref, kin)
        return np.einsum("hg,hg->h", ref.weights, w_iso) + v0 * self.bulk / 2 * log_jbar**2

    def forces(self, ref: ReferenceGradients, kin: Kinematics, n_nodes: int) -> np.ndarray:
        """(N, 3) internal nodal forces dE/du, N: the isochoric stress
        ``P = mu J^(-2/3) (F - I1/3 F^-T)`` at the Gauss points, and ``K ln Jbar / Jbar dV/du``
        with ``dV/du_a = sum_g w J g_a``."""
        a, i1_minus_3 = self._isochoric(kin)
        inverse_t = np.swapaxes(kin.inverse, -1, -2)
        stress = (self.mu * a)[..., None, None] * (
            kin.f_minus_inverse_t() - (i1_minus_3 / 3)[..., None, None] * inverse_t
        )
        v0, log_jbar = self._dilatation(ref, kin)
        g = spatial_gradients(ref, kin)
        dv = np.einsum("hg,hgai->hai", ref.weights * kin.det, g)
        pressure = self.bulk * log_jbar / np.exp(log_jbar)  # K ln Jbar / Jbar, Pa
        return internal_forces(ref, stress, n_nodes) + _scatter(
            pressure[:, None, None] * dv, ref.hexahedra, n_nodes
        )

    def tangents(self, ref: ReferenceGradients, kin: Kinematics) -> np.ndarray:
        """(H, 8, 8, 3, 3) element blocks d f_ai / d u_bk, N/m.

        Isochoric, per Gauss point, with c = w mu J^(-2/3), q_a = F dN_a/dX, g_a = F^-T dN_a/dX::

            c [ d_ik dN_a.dN_b - 2/3 (q_ai g_bk + g_ai q_bk) + 2/9 I1 g_ai g_bk + I1/3 g_ak g_bi ]

        Volumetric, per element: ``K (1 - ln Jbar) / (Jbar^2 V0) dV_ai dV_bk`` plus
        ``K ln Jbar / Jbar sum_g w J (g_ai g_bk - g_ak g_bi)``.
        """
        n = len(ref.weights)
        a, i1_minus_3 = self._isochoric(kin)
        c = self.mu * a * ref.weights
        g = spatial_gradients(ref, kin)
        q = ref.gradients + np.einsum("hgij,hgaj->hgai", kin.displacement_gradient, ref.gradients)
        mixed = _outer(q, g, c)
        both = _outer(g, g, c * (3 + i1_minus_3))
        laplacian = np.einsum("hg,hgaj,hgbj->hab", c, ref.gradients, ref.gradients)
        v0, log_jbar = self._dilatation(ref, kin)
        jbar = np.exp(log_jbar)
        dv = np.einsum("hg,hgai->hai", ref.weights * kin.det, g).reshape(n, 24)
        curvature = self.bulk * (1 - log_jbar) / (jbar**2 * v0)
        volume = curvature[:, None, None] * dv[:, :, None] * dv[:, None, :]
        jacobian = _outer(g, g, ref.weights * kin.det)
        pressure = (self.bulk * log_jbar / jbar)[:, None, None]
        direct = -2 / 3 * (mixed + np.swapaxes(mixed, 1, 2)) + 2 / 9 * both + volume
        direct += pressure * jacobian
        crossed = both / 3 - pressure * jacobian
        return _blocks(n, direct, crossed, laplacian)


NeoHookeanLaw = CompressibleNeoHookean | MeanDilatationNeoHookean


def neo_hookean_law(mu: float, lam: float, integration: str) -> NeoHookeanLaw:
    """The neo-Hookean solid of Lame constants ``mu``, ``lam`` (Pa) integrated as
    ``integration`` says: ``"selective"`` (mean dilatation) or ``"full"`` (2x2x2)."""
    if integration == "selective":
        return MeanDilatationNeoHookean(mu, lam + 2 * mu / 3)
    if integration == "full":
        return CompressibleNeoHookean(mu, lam)
    raise ValueError(f"unknown integration {integration!r} (use 'selective' or 'full')")
