"""When a dynamic run has settled: near its static equilibrium, at every lattice size
(docs/explanation/physics/settle.md, *Two criteria, one promise*).

- **The force criterion** (the paper's): the largest unbalanced nodal force below a tolerance
  times the largest applied force. Not scale-free, so kept where the spec names
  ``fpm.settle_tolerance`` or there are no modes to read (the paper method; a mechanism).
- **The distance criterion** (1): ``|r| < settle_distance * lambda * |u|``, 2-norms over the
  list's unknowns, lambda the *mode stiffness* (N/m, :func:`mode_stiffness`): a bound on the
  distance from the static equilibrium below ``fpm.settle_distance`` times the displacement.
- **The target criterion** (2), where the static equilibrium u* is known:
  ``sum_i sqrt(|x_i - x*_i|^2 + m_i |v_i|^2 / lambda) < distance * sum_i |u*_i|`` in the
  calibration's norm (paper Eq. 2), the velocities' term the reach of a swing still under way;
  settle distance 'auto' (:func:`case_distances`) is :data:`SHARE` of the load cases' static
  discrepancy, so the settled cost is within (1 + SHARE) of the static cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ..model.spec import ProblemSpec

FORCE_TOLERANCE = 1e-5
"""The force criterion's tolerance where the spec names none but the distance criterion has
no modes to read (the paper method; a mechanism): settled when the largest unbalanced nodal
force is below this times the largest applied nodal force."""

PROMISE = 1.0
"""The settled state is promised within this times its settle distance of its static
equilibrium, measured; the result warns where it is not."""

SHARE = 0.05
"""settle_distance 'auto': the load cases' settle distance is this share of their static
equilibria's discrepancy against the reference, relative and together
(``sum |u* - u_ref| / sum |u*|`` over every case): the settled cost is then within
(1 + SHARE) times the static cost."""
NOMINAL, FLOOR = 0.01, 1e-4
"""settle_distance 'auto': at most NOMINAL (also its value where there is no reference to read:
fpm.simulate, an exported model), at least FLOOR (a fit that matches its reference exactly
would otherwise never settle)."""


@dataclass(frozen=True, eq=False)
class SettleCriterion:
    """When a run of one load case is settled, checked every sweep by the kernel
    (:func:`fpm.dynamics.voigt.run_steps`). Each field None: that criterion is not used; a
    criterion with none settles never.

    Attributes:
        force_tolerance: the force criterion: settled once the largest unbalanced nodal force
            is below this times the largest applied nodal force (dimensionless; 0 never
            settles).
        stiffness: the distance criterion (1): settled once the 2-norm of the unbalanced nodal
            forces (N) is below this (N/m, the settle distance times the mode stiffness
            lambda) times the 2-norm of the displacements (m).
        target: the target criterion (2): the static equilibrium's displacements (N, 3), m,
            towards which the run settles; with it the two criteria above are not read.
        slowness: the target criterion's weight of the velocities, m/N (the settle distance
            over lambda): each node's reach adds ``slowness * m_i |v_i|^2`` (m^2) to its
            squared distance.
        reach: the target criterion's threshold, m: settled once the sum of the nodal reaches
            is below it.
    """

    force_tolerance: float | None = None
    stiffness: float | None = None
    target: np.ndarray | None = None
    slowness: float | None = None
    reach: float | None = None

    def __post_init__(self) -> None:
        given = [self.target is not None, self.slowness is not None, self.reach is not None]
        if any(given) and not all(given):
            raise ValueError("the target criterion needs its target, slowness and reach")


def nominal_distance(spec: ProblemSpec) -> float:
    """The spec's settle_distance as a number where nothing else is known: its value, or
    :data:`NOMINAL` for 'auto'."""
    value = spec.fpm.settle_distance
    return NOMINAL if value == "auto" else float(value)


def nodal_size(u: np.ndarray) -> float:
    """The calibration's norm of displacements ``u`` (N, 3) m: the sum of the nodal distances
    (paper Eq. 2), m."""
    return float(np.sqrt((u * u).sum(axis=-1)).sum())


def case_distances(
    spec: ProblemSpec, static: np.ndarray, reference: np.ndarray | None
) -> list[float]:
    """Each load case's settle distance: the spec's settle_distance, or for 'auto' SHARE of the
    cases' static discrepancy together, ``sum_j sum |u*_j - u_ref_j| / sum_j sum |u*_j|``
    (:func:`nodal_size` of ``static`` and ``reference``, (L, N, 3) m; None: :data:`NOMINAL`),
    clipped to [FLOOR, NOMINAL], the same for every case."""
    value = spec.fpm.settle_distance
    if value != "auto" or reference is None:
        return [nominal_distance(spec)] * len(static)
    size = sum(nodal_size(u) for u in static)
    off = sum(nodal_size(u - ref) for u, ref in zip(static, reference, strict=True))
    share = SHARE * off / size if size > 0 else NOMINAL
    return [float(min(max(share, FLOOR), NOMINAL))] * len(static)


def force_tolerance(spec: ProblemSpec) -> float:
    """The force criterion's tolerance: the spec's ``fpm.settle_tolerance``, or
    :data:`FORCE_TOLERANCE` where it names none."""
    named = spec.fpm.settle_tolerance
    return FORCE_TOLERANCE if named is None else float(named)


def by_distance(spec: ProblemSpec) -> bool:
    """Whether runs settle on the distance criterion (2): the spec names no
    ``fpm.settle_tolerance`` and the method has modes to read (two-stage)."""
    return spec.fpm.settle_tolerance is None and spec.annealing.method != "paper"


def mode_stiffness(w2: np.ndarray, shapes: np.ndarray) -> float:
    """The mode stiffness lambda of (1), N/m: K's lowest eigenvalue on the span of the slowest
    modes, from their squared frequencies ``w2`` (k,) 1/s^2 and M-orthonormal ``shapes`` (3M, k)
    kg^-1/2 (so ``Phi^T K Phi = diag(w2)``): the lowest generalised eigenvalue of
    ``diag(w2)`` against ``Phi^T Phi``."""
    gram = shapes.T @ shapes
    return float(sla.eigh(np.diag(w2), gram, eigvals_only=True)[0])


def estimated_distance(residual: float, displacement: float, stiffness: float) -> float:
    """A settled state's estimated distance from its static equilibrium, relative to its
    displacement: ``residual / (lambda * displacement)``, with ``residual`` the 2-norm of its
    unbalanced nodal forces (N), ``displacement`` the 2-norm of its displacements (m) and
    ``stiffness`` the list's mode stiffness lambda (N/m); inf when nothing moved."""
    if not displacement > 0 or not stiffness > 0:
        return float("inf")
    return float(residual / (stiffness * displacement))


def measured_distance(settled: np.ndarray, static: np.ndarray) -> float:
    """The settled displacements' (N, 3) m distance from the static equilibrium's (N, 3) m,
    relative to the equilibrium's, in the calibration's norm: ``nodal_size(settled - static)
    / nodal_size(static)``."""
    size = nodal_size(static)
    if not size > 0:
        return float("inf")
    return nodal_size(settled - static) / size


def run_criterion(
    spec: ProblemSpec,
    settle_stiffness: float | None,
    static: np.ndarray | None = None,
    distance: float | None = None,
) -> SettleCriterion:
    """A run's settle criterion (``settle=`` of :meth:`fpm.dynamics.simulation.FpmModel.start`):
    the force criterion (``settle_stiffness`` None), the distance criterion (1) at
    ``settle_stiffness`` = the nominal distance times lambda (N/m, :func:`nominal_distance`),
    or, given ``static`` (N, 3) the run's static equilibrium displacements (m) and its settle
    ``distance``, the target criterion (2) with the same lambda."""
    if settle_stiffness is None:
        return SettleCriterion(force_tolerance=force_tolerance(spec))
    if static is None or distance is None:
        return SettleCriterion(stiffness=float(settle_stiffness))
    return SettleCriterion(
        target=static,
        reach=distance * nodal_size(static),
        slowness=nominal_distance(spec) / float(settle_stiffness),
    )
