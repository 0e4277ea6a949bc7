"""Transversely isotropic elasticity: the material's stiffness tensor and the lattice's closed form.

A transversely isotropic solid (``material.type: "transversely-isotropic"``, docs/physics.md,
*Transversely isotropic material*) is isotropic in the plane normal to its ``axis`` and has five
constants: the Young's moduli along the axis (``E_a``) and across it (``E_t``), the in-plane
Poisson's ratio ``nu_t`` (a stretch across the axis narrows the other in-plane direction by
``nu_t``), the axial one ``nu_a`` (a stretch along the axis narrows every in-plane direction by
``nu_a``) and the shear modulus ``G_a`` of the planes that contain the axis; the in-plane one is
``G_t = E_t / (2 (1 + nu_t))``. In a frame whose third axis is the material axis the compliance
(Voigt order xx, yy, zz, xy, yz, zx, engineering shear strains, as :mod:`fpm.fem.elasticity`) is

    S = [[ 1/E_t,    -nu_t/E_t, -nu_a/E_a, 0,     0,     0    ],
         [-nu_t/E_t,  1/E_t,    -nu_a/E_a, 0,     0,     0    ],
         [-nu_a/E_a, -nu_a/E_a,  1/E_a,    0,     0,     0    ],
         [ 0,         0,         0,        1/G_t, 0,     0    ],
         [ 0,         0,         0,        0,     1/G_a, 0    ],
         [ 0,         0,         0,        0,     0,     1/G_a]]

and ``C = S^-1`` (:func:`stiffness_tensor` turns it to the solid's axes). S is positive definite
exactly when the moduli are > 0, ``-1 < nu_t < 1`` and ``1 - nu_t - 2 nu_a^2 E_t / E_a > 0``.

**In the lattice** (families+volume, :mod:`fpm.model.stiffness`) the paper's per-axis stiffness
scale (Fig. 5) is fitted with the families: a spring along unit vector e gets its assembled
stiffness times ``1 + (s - 1) (e . a)^2`` (``s`` the *axial scale*; for an axis along z this is
the paper's ``stiffness_scale = (1, 1, s)``). With the face and body diagonals scaled by
``(1 + s)/2`` and ``(2 + s)/3``, a regular lattice of spacing h with axis along z has the
continuum constants (:func:`lattice_constants`)

    C11 = (k1 + k2 (3 + s)/2 + b) / h + kappa     C33 = (k1 s + k2 (1 + s) + b) / h + kappa
    C12 = (k2 + b) / h + kappa                    C13 = (k2 (1 + s)/2 + b) / h + kappa
    C44 = (k2 (1 + s)/2 + b) / h                  C66 = (k2 + b) / h,   b = 4 k3 (2 + s) / 9

(``s = 1``: the isotropic lattice of docs/physics.md). :func:`closed_form_start` picks
``(k1, k2, k3, kappa, s)`` nearest the material's six constants (linear least squares in the
k's and kappa, each constant's misfit relative to it, for each s; s by a scan in log s refined
by Brent): the fit's start.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.optimize import lsq_linear, minimize_scalar

VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (2, 0))
"""Tensor index pairs of the Voigt rows xx, yy, zz, xy, yz, zx (:mod:`fpm.fem.elasticity`)."""

SCALE_RANGE = (1e-2, 1e2)
"""The axial scales the closed form considers."""
WEIGHT_FLOOR = 0.05
"""The closed form weighs each constant's misfit relative to it (at least this fraction of the
largest), so the shear constants count as much as the stiffer normal ones."""
BODY_PENALTY = 1e-3
"""A slight pull of k3 towards 0: an isotropic target is met exactly by a line of lattices
(``k1 = k2 + 8 k3 / 3``), and this picks the continuum start's (``k3 = 0``) among them."""


def local_compliance(
    e_axial: float, e_transverse: float, nu_transverse: float, nu_axial: float, g_axial: float
) -> np.ndarray:
    """(6, 6) compliance S, 1/Pa, in a frame whose third axis is the material axis."""
    s = np.zeros((6, 6))
    s[0, 0] = s[1, 1] = 1.0 / e_transverse
    s[0, 1] = s[1, 0] = -nu_transverse / e_transverse
    s[0, 2] = s[2, 0] = s[1, 2] = s[2, 1] = -nu_axial / e_axial
    s[2, 2] = 1.0 / e_axial
    s[3, 3] = 2.0 * (1.0 + nu_transverse) / e_transverse
    s[4, 4] = s[5, 5] = 1.0 / g_axial
    return s


def frame(axis: Any) -> np.ndarray:
    """(3, 3) rotation whose columns are two unit vectors normal to ``axis`` and the unit axis
    (local coordinates to the solid's: x = R x_local)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(helper, a)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(a, e1), a])


def rotate(c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(6, 6) Voigt stiffness ``c`` given in a local frame, in the frame ``x = r x_local``
    (engineering shear strains: Voigt entries are the tensor's components)."""
    t = np.zeros((3, 3, 3, 3))
    for p, (i, j) in enumerate(VOIGT):
        for q, (k, m) in enumerate(VOIGT):
            for a, b in {(i, j), (j, i)}:
                for e, f in {(k, m), (m, k)}:
                    t[a, b, e, f] = c[p, q]
    t = np.einsum("ip,jq,kr,ls,pqrs->ijkl", r, r, r, r, t, optimize=True)
    return np.array([[t[i, j, k, m] for k, m in VOIGT] for i, j in VOIGT])


def constants(material: Any) -> tuple[float, float, float, float, float]:
    """(E_a, E_t, nu_t, nu_a, G_a) of a :class:`fpm.model.spec.TransverselyIsotropicMaterial`."""
    m = material
    return (
        m.youngs_modulus_axial,
        m.youngs_modulus_transverse,
        m.poisson_ratio_transverse,
        m.poisson_ratio_axial,
        m.shear_modulus_axial,
    )


def local_stiffness(material: Any) -> np.ndarray:
    """(6, 6) C, Pa, of a transversely isotropic material in its own frame (axis third)."""
    return np.linalg.inv(local_compliance(*constants(material)))


def stiffness_tensor(material: Any) -> np.ndarray:
    """(6, 6) C, Pa, of a transversely isotropic material in the solid's axes (Voigt order and
    engineering shear of :func:`fpm.fem.elasticity.constitutive_matrix`)."""
    return rotate(local_stiffness(material), frame(material.axis))


def axial_cosines(directions: np.ndarray, axis: Any) -> np.ndarray:
    """(S,) ``(e . a)^2`` of unit spring directions ``directions`` (S, 3) and the unit axis."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    return (directions @ a) ** 2


def _design(s: float, n_families: int) -> np.ndarray:
    """(6, n_families + 1) the lattice constants C11, C33, C12, C13, C44, C66 as linear in
    (k1/h, k2/h, k3/h, kappa) at axial scale ``s`` (this module's docstring)."""
    b = 4.0 * (2.0 + s) / 9.0
    rows = np.array(
        [
            [1.0, (3.0 + s) / 2, b, 1.0],
            [s, 1.0 + s, b, 1.0],
            [0.0, 1.0, b, 1.0],
            [0.0, (1.0 + s) / 2, b, 1.0],
            [0.0, (1.0 + s) / 2, b, 0.0],
            [0.0, 1.0, b, 0.0],
        ]
    )
    return np.concatenate([rows[:, :n_families], rows[:, 3:]], axis=1)


def lattice_constants(k: Any, kappa: float, s: float, h: float) -> np.ndarray:
    """(6,) C11, C33, C12, C13, C44, C66, Pa, of a regular lattice (spacing h, m; axis along z)
    with family stiffnesses ``k`` (N/m, 1 to 3 of them), volume stiffness ``kappa`` (Pa) and
    axial scale ``s``."""
    k = np.asarray(k, dtype=float)
    return _design(s, len(k)) @ np.append(k / h, kappa)


def target_constants(c: np.ndarray) -> np.ndarray:
    """(6,) C11, C33, C12, C13, C44, C66 of a local-frame TI stiffness ``c`` (6, 6)."""
    return np.array([c[0, 0], c[2, 2], c[0, 1], c[0, 2], c[4, 4], c[3, 3]])


def closed_form_start(
    material: Any, h: float, n_families: int, floor: float
) -> tuple[list[float], float, float, float]:
    """The lattice parameters nearest the material's constants (this module's docstring).

    Args:
        material: a transversely isotropic material.
        h: lattice spacing, m.
        n_families: spring families present (2 for axis+face, 3 for full).
        floor: the smallest k / h and kappa considered, Pa (a fraction of the shear modulus).

    Returns:
        (k per family, N/m; kappa, Pa; axial scale s; root mean square relative misfit over the
        six constants).
    """
    target = target_constants(local_stiffness(material))
    weight = 1.0 / np.maximum(np.abs(target), WEIGHT_FLOOR * np.abs(target).max())
    lower = np.full(n_families + 1, floor)
    scale = float(np.abs(target).max())

    penalty = np.zeros((1, n_families + 1))
    if n_families == 3:  # of the lattices that fit equally well, the one with the least k3
        penalty[0, 2] = BODY_PENALTY / target[5]

    def solve(s: float) -> tuple[np.ndarray, float]:
        design = _design(s, n_families)
        a = np.concatenate([design * weight[:, None], penalty]) * scale
        b = np.append(target * weight, 0.0)
        x = lsq_linear(a, b, bounds=(lower / scale, np.inf), method="bvls").x * scale
        return x, float(np.linalg.norm((design @ x - target) * weight) / np.sqrt(len(target)))

    logs = np.linspace(np.log(SCALE_RANGE[0]), np.log(SCALE_RANGE[1]), 81)
    misfits = [solve(float(np.exp(y)))[1] for y in logs]
    best = int(np.argmin(misfits))
    lo, hi = logs[max(best - 1, 0)], logs[min(best + 1, len(logs) - 1)]
    r = minimize_scalar(
        lambda y: solve(float(np.exp(y)))[1], bounds=(lo, hi), method="bounded",
        options={"xatol": 1e-6},
    )  # fmt: skip
    y = float(r.x) if r.fun <= misfits[best] else float(logs[best])
    s = float(np.exp(y))
    x, misfit = solve(s)
    return [float(v) * h for v in x[:-1]], float(x[-1]), s, misfit
