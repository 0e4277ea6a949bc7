"""The model's force terms, in one place: what every solver, the fit and the exports read.

The FPM's internal energy at positions x = X + u is the sum of its terms (docs/physics.md,
*The model's energy*):

- **springs** (paper Eq. 1): ``sum_s 1/2 k_s (|x_j - x_i| - L_s)^2`` over the (S,) springs,
  k_s in N/m;
- **volume** (:mod:`fpm.model.volume`): ``sum_c 1/2 kappa_c (V_c - V0_c)^2 / V0_c`` over the
  lattice cells (hexahedra), kappa_c in Pa; absent (None) in the paper's model.

A :class:`Stiffness` holds the parameters of every term; :func:`fpm.model.stiffness.model_stiffness`
builds it from the fitted parameters theta. The compiled hot loops (the dynamic step in
:mod:`fpm.dynamics.voigt`, the static solver in :mod:`fpm.dynamics.equilibrium`) take its arrays;
:func:`internal_energy` and :func:`internal_forces` here are the plain NumPy definitions that
the tests and the export check them against. A new term is a new field here and its module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .problem import Problem

if TYPE_CHECKING:
    from .volume import Cells


@dataclass(frozen=True)
class Stiffness:
    """The stiffness of every force term.

    Attributes:
        springs: (S,) stiffness of every spring, N/m (stiffness_scale included).
        volume: (H,) volume stiffness kappa of every cell, Pa, aligned with the solid's
            hexahedra; None: no volume term (the paper's model).
    """

    springs: np.ndarray
    volume: np.ndarray | None = None

    @classmethod
    def of(cls, value: Stiffness | np.ndarray) -> Stiffness:
        """``value`` as a Stiffness ((S,) spring stiffnesses alone: no volume term)."""
        if isinstance(value, Stiffness):
            return value
        return cls(np.asarray(value, dtype=float))

    def parameters(self) -> np.ndarray:
        """Every stiffness as one flat vector (springs, then cells), for comparisons."""
        if self.volume is None:
            return self.springs
        return np.concatenate([self.springs, self.volume])


def cells(problem: Problem) -> Cells:
    """The problem's lattice cells (:class:`fpm.model.volume.Cells`), built once and kept.

    Raises:
        ValueError: the geometry has no hexahedra (a ``network``).
    """
    from .volume import Cells  # compiled (numba): loaded only where a volume term is used

    found = problem.cache.cells
    if found is None:
        hexahedra = problem.solid.elements()
        if hexahedra is None:
            raise ValueError("a network geometry has no cells: it cannot carry a volume term")
        found = problem.cache.cells = Cells.from_hexahedra(problem.nodes, hexahedra)
    return found


def internal_energy(problem: Problem, stiffness: Stiffness, displacements: np.ndarray) -> float:
    """The model's internal energy, J, at nodal ``displacements`` (N, 3), m."""
    s = problem.solid.springs
    x = problem.nodes + displacements
    stretch = np.linalg.norm(x[s[:, 1]] - x[s[:, 0]], axis=1) - problem.rest_lengths
    energy = 0.5 * float(np.sum(stiffness.springs * stretch * stretch))
    if stiffness.volume is not None:
        from .volume import volume_energy

        energy += volume_energy(cells(problem), stiffness.volume, displacements)
    return energy


def internal_forces(
    problem: Problem, stiffness: Stiffness, displacements: np.ndarray
) -> np.ndarray:
    """(N, 3) internal nodal forces, N (minus the energy's gradient) at ``displacements``."""
    s = problem.solid.springs
    x = problem.nodes + displacements
    r = x[s[:, 1]] - x[s[:, 0]]
    length = np.linalg.norm(r, axis=1)
    t = (stiffness.springs * (length - problem.rest_lengths) / length)[:, None] * r
    forces = np.zeros_like(displacements)
    np.add.at(forces, s[:, 0], t)
    np.add.at(forces, s[:, 1], -t)
    if stiffness.volume is not None:
        from .volume import volume_forces

        forces += volume_forces(cells(problem), stiffness.volume, displacements)
    return forces
