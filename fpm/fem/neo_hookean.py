"""Compressible neo-Hookean hexahedra, total Lagrangian: stress, nodal forces and tangent.

Strain energy per unit reference volume, Pa (J/m^3)::

    W(F) = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2,    I1 = tr(F^T F),  J = det F

with the Lame constants ``mu``, ``lambda`` of E and nu
(:func:`fpm.model.spec.lame_constants`). Its first Piola-Kirchhoff stress and the derivative
of that stress (the material tangent), Pa::

    P = mu (F - F^-T) + lambda ln J F^-T
    dP_iJ/dF_kL = mu d_ik d_JL + (mu - lambda ln J) Finv_Li Finv_Jk + lambda Finv_Ji Finv_Lk

At F = I the tangent is the isotropic elasticity tensor of
:func:`fpm.fem.elasticity.constitutive_matrix`, so small loads reproduce the linear FEM. The
elements are the linear FEM's: 8-node trilinear hexahedra (:mod:`fpm.model.hexahedron` order), 2x2x2
Gauss points, quantities of the reference (undeformed) configuration fixed once
(:func:`reference_gradients`). Everything is vectorised over elements and Gauss points: H
hexahedra, G = 8 Gauss points, 8 local nodes a, b; indices i, k spatial, J, L material axes.
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


def kinematics(ref: ReferenceGradients, u: np.ndarray) -> Kinematics:
    """:class:`Kinematics` of nodal displacements ``u`` (N, 3), m.

    Small strains lose no digits: ``J - 1 = tr H + (tr^2 H - tr H^2) / 2 + det H`` and (in
    :func:`first_piola`) ``F - F^-T = H + (F^-1 H)^T`` are formed from H, not from F - I.
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
    h = kin.displacement_gradient
    return (
        mu * (h + np.swapaxes(kin.inverse @ h, -1, -2))
        + (lam * kin.log_j)[..., None, None] * inverse_t
    )


def strain_energy(kin: Kinematics, mu: float, lam: float) -> np.ndarray:
    """(H, G) W, J/m^3: I1 - 3 = 2 tr H + H:H."""
    h = kin.displacement_gradient
    i1_minus_3 = 2 * np.einsum("...ii->...", h) + np.einsum("...ij,...ij->...", h, h)
    return mu / 2 * i1_minus_3 - mu * kin.log_j + lam / 2 * kin.log_j**2


def internal_forces(ref: ReferenceGradients, stress: np.ndarray, n_nodes: int) -> np.ndarray:
    """(N, 3) nodal internal forces f_ai = sum_g w P_iJ dN_a/dX_J, N, of P (H, G, 3, 3), Pa."""
    per_point = np.matmul(ref.gradients, np.swapaxes(stress, -1, -2))  # (H, G, 8, 3)
    per_element = np.einsum("hg,hgai->hai", ref.weights, per_point)
    index = ref.hexahedra.ravel()
    flat = per_element.reshape(-1, 3)
    return np.stack([np.bincount(index, flat[:, i], n_nodes) for i in range(3)], axis=1)


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
    h = len(ref.weights)
    g = np.einsum("hgji,hgaj->hgai", kin.inverse, ref.gradients, optimize=True)
    g = g.reshape(h, 8, 24)
    lam_part = np.matmul(np.swapaxes(g * (lam * ref.weights)[..., None], 1, 2), g)
    c = (mu - lam * kin.log_j) * ref.weights
    cross = np.matmul(np.swapaxes(g * c[..., None], 1, 2), g)  # [(a, k), (b, i)]
    k = lam_part.reshape(h, 8, 3, 8, 3) + cross.reshape(h, 8, 3, 8, 3).swapaxes(2, 4)
    k = k.transpose(0, 1, 3, 2, 4)  # (H, a, b, i, k)
    k[..., [0, 1, 2], [0, 1, 2]] += mu * ref.laplacian[..., None]
    return k
