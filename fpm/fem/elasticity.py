"""Linear elasticity on the 8-node hexahedron (paper Sec. 4.1): C, strains, element K
(shape functions and Gauss points: :mod:`fpm.model.hexahedron`).

Strains and stresses are Voigt vectors in the order (xx, yy, zz, xy, yz, zx) with engineering
shear strains gamma_xy = du/dy + dv/dx, so that ``sigma = C @ epsilon`` with ``C`` exactly as the
paper prints it. An element's 24 unknowns are node-major: (u0, v0, w0, u1, v1, w1, ..., w7), local
nodes in :mod:`fpm.model.hexahedron` order.
"""

from __future__ import annotations

import numpy as np

from ..model.hexahedron import GAUSS_POINTS, NATURAL, jacobians, shape_function_gradients

SHEAR_PAIRS = ((0, 1), (1, 2), (2, 0))
"""Axes (a, c) of the Voigt shear rows 3, 4, 5: xy, yz, zx."""


def constitutive_matrix(youngs_modulus: float, poisson_ratio: float) -> np.ndarray:
    """(6, 6) isotropic elasticity matrix C, Pa (paper Sec. 4.1, engineering shear strains)."""
    nu = poisson_ratio
    c = np.zeros((6, 6))
    c[:3, :3] = nu
    c[np.arange(3), np.arange(3)] = 1 - nu
    c[np.arange(3, 6), np.arange(3, 6)] = (1 - 2 * nu) / 2
    return youngs_modulus / ((1 + nu) * (1 - 2 * nu)) * c


def strain_displacement(gradients: np.ndarray) -> np.ndarray:
    """(H, 6, 3n) B with epsilon = B u (Voigt xx, yy, zz, xy, yz, zx, engineering shear), from
    physical gradients dN_i/dx_b (H, n, 3), 1/m, for any element of n nodes (node-major u)."""
    h, n = gradients.shape[:2]
    b = np.zeros((h, 6, n, 3))
    for a in range(3):
        b[:, a, :, a] = gradients[:, :, a]  # normal strains
    for row, (a, c) in enumerate(SHEAR_PAIRS, start=3):  # gamma_ac = du_a/dx_c + du_c/dx_a
        b[:, row, :, a] = gradients[:, :, c]
        b[:, row, :, c] = gradients[:, :, a]
    return b.reshape(h, 6, 3 * n)


def physical_gradients(coords: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dN_i/dx (H, 8, 3), 1/m, and det J (H,) at natural ``point`` for ``coords`` (H, 8, 3)."""
    jac = jacobians(coords, point)
    grad = np.einsum("na,hba->hnb", shape_function_gradients(point), np.linalg.inv(jac))
    return grad, np.linalg.det(jac)


INTEGRATIONS = ("selective", "full")
"""How :func:`element_stiffness` integrates (``reference.integration`` in the spec)."""

VOLUMETRIC = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
"""m: the volumetric strain is m . epsilon (Voigt order)."""


def bulk_modulus(c: np.ndarray) -> float:
    """kappa = (C11 + 2 C12) / 3, Pa, of an isotropic C (6, 6): lambda + 2 mu / 3."""
    return float(c[0, 0] + 2 * c[0, 1]) / 3


def element_stiffness(coords: np.ndarray, c: np.ndarray, integration: str = "full") -> np.ndarray:
    """(H, 24, 24) element stiffness K_e, N/m, for ``coords`` (H, 8, 3).

    ``"full"``: sum over the 2x2x2 Gauss points of B^T C B det J (exact for a
    parallelepiped; locks volumetrically as nu approaches 1/2).

    ``"selective"``: the deviatoric part ``C - kappa m m^T`` (kappa the bulk modulus) at the
    2x2x2 Gauss points, plus the volumetric part on the element's mean dilatation,
    ``kappa V b_bar b_bar^T`` with ``b_bar = (1/V) int m^T B dV``: exactly K of B-bar with the
    mean dilatation (``B_bar = B + m (b_bar - m^T B) / 3``). On a parallelepiped b_bar is B's
    volumetric row at the centre, so this is one-point integration of the volumetric part.
    Uniform strains are still reproduced exactly (patch test).

    The caller checks det J > 0.
    """
    if integration not in INTEGRATIONS:
        raise ValueError(f"unknown integration {integration!r} (use 'selective' or 'full')")
    if integration == "selective" and not is_isotropic(c):
        return mean_dilatation_stiffness(coords, c)
    ke = np.zeros((len(coords), 24, 24))
    if integration == "full":
        for point in GAUSS_POINTS:
            grad, det = physical_gradients(coords, point)
            b = strain_displacement(grad)
            ke += np.einsum("hpa,pq,hqb->hab", b, c, b, optimize=True) * det[:, None, None]
        return ke
    kappa = bulk_modulus(c)
    deviatoric = c - kappa * np.outer(VOLUMETRIC, VOLUMETRIC)
    divergence = np.zeros((len(coords), 24))  # int m^T B dV
    volume = np.zeros(len(coords))
    for point in GAUSS_POINTS:
        grad, det = physical_gradients(coords, point)
        b = strain_displacement(grad)
        ke += np.einsum("hpa,pq,hqb->hab", b, deviatoric, b, optimize=True) * det[:, None, None]
        divergence += grad.reshape(len(coords), 24) * det[:, None]
        volume += det
    ke += kappa * np.einsum("ha,hb->hab", divergence, divergence) / volume[:, None, None]
    return ke


def is_isotropic(c: np.ndarray) -> bool:
    """``c`` (6, 6) has the isotropic form of :func:`constitutive_matrix` (to 1e-12 of its
    largest entry): equal normal and equal off-diagonal entries, shear ``(C11 - C12) / 2``,
    no coupling between normal and shear rows."""
    c = np.asarray(c, dtype=float)
    c11, c12 = c[0, 0], c[0, 1]
    iso = np.zeros((6, 6))
    iso[:3, :3] = c12
    iso[np.arange(3), np.arange(3)] = c11
    iso[np.arange(3, 6), np.arange(3, 6)] = (c11 - c12) / 2
    return bool(np.abs(c - iso).max() <= 1e-12 * np.abs(c).max())


def mean_dilatation_stiffness(coords: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(H, 24, 24) K_e, N/m, of the B-bar element with the mean dilatation for any (6, 6) C
    (an anisotropic one, :mod:`fpm.fem.materials`): ``sum_g B_bar^T C B_bar det J`` over the
    2x2x2 Gauss points, ``B_bar = B + m (b_bar - m^T B) / 3``, ``b_bar = (1/V) int m^T B dV``.
    For an isotropic C it equals the split form of :func:`element_stiffness`; uniform strains
    are reproduced exactly (patch test)."""
    points = [physical_gradients(coords, point) for point in GAUSS_POINTS]
    volume = np.sum([det for _, det in points], axis=0)
    mean = np.sum([grad.reshape(len(coords), 24) * det[:, None] for grad, det in points], axis=0)
    mean /= volume[:, None]
    ke = np.zeros((len(coords), 24, 24))
    for grad, det in points:
        b = strain_displacement(grad)
        b += VOLUMETRIC[None, :, None] * (mean - grad.reshape(len(coords), 24))[:, None, :] / 3
        ke += np.einsum("hpa,pq,hqb->hab", b, c, b, optimize=True) * det[:, None, None]
    return ke


def min_jacobian_determinants(coords: np.ndarray) -> np.ndarray:
    """(H,) smallest det J over the Gauss points and corners: <= 0 flags an inverted hexahedron."""
    points = np.concatenate([GAUSS_POINTS, NATURAL])
    return np.min([np.linalg.det(jacobians(coords, p)) for p in points], axis=0)
