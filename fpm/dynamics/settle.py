"""When a dynamic run has settled: near its static equilibrium, at every lattice size
(docs/explanation/physics/settle.md).

A run of one load case stops once it is settled. Near the static equilibrium x* of its list,
with K the free nodes' tangent (SPD) and r the unbalanced force (N), the error is
``x - x* = -K^-1 r``. A criterion on the force alone ("largest |r_i| below a tolerance times
the largest applied force", the paper's) is not scale-free: K's lowest eigenvalues fall like
h^2 as the lattice is refined, so the same force tolerance lets the state sit further from rest
on a finer lattice (the figures: docs/explanation/physics/settle.md).

**The distance criterion.** With Euclidean norms over the list's unknowns,
``|x - x*| <= |r| / lambda_min(K)``: a run is settled when

    |r| < settle_distance * lambda * |u|                                               (1)

(u = x - rest, |.| the 2-norm over the list's nodes), i.e. when that bound on its distance from
the static equilibrium is below ``fpm.settle_distance`` times its displacement. lambda, the
*mode stiffness* (N/m, :func:`mode_stiffness`), is K's lowest eigenvalue estimated on the span
of the list's slowest modes (:mod:`fpm.dynamics.modes`; a Rayleigh-Ritz value: with
M-orthonormal shapes Phi, the lowest eigenvalue of ``diag(w^2)`` against ``Phi^T Phi``). Late
in a run the error lives in those modes, where the bound is nearly an equality. Both sides of
(1) scale alike with the load and with the lattice (lambda falls like h^2 as the lattice is
refined, and with it the force the criterion accepts): it means the same on a 4.7k- and a
93.7k-node organ. (1) is the kernel's ``settle_stiffness = settle_distance * lambda``
(:func:`fpm.dynamics.voigt.run_steps`), checked every sweep. 2-norms, not largest nodal
values: the calibration's cost sums over every node, and a point load's peak displacement is
many times the typical one, so a distance relative to the peak would let the state sit well
above the static cost while its peak is close to equilibrium.

**The target criterion.** Where the static equilibrium u* of the list is known (the damping
stage solves it before its d search), the distance need not be bounded: it is measured, in the
calibration's own norm (paper Eq. 2 sums the nodal distances |.|_1 = sum_i |.|_i over the
nodes). A run is settled when its *reach* from there is below its settle distance times the
equilibrium's displacement,

    sum_i sqrt(|x_i - x*_i|^2 + m_i |v_i|^2 / lambda) < distance * sum_i |u*_i|          (2)

The first term is the distance itself; the second is how far the velocities could still
carry each node along the slowest mode (for that mode, the square of its swing's amplitude),
so a run that passes through the equilibrium on its way to an overshoot is not called settled.
In this norm the triangle inequality bounds what settling adds to the fit's figures: a case
settled at distance delta has a cost within delta * sum |u*| of its static cost. So the default
distance ('auto', :func:`case_distances`) is :data:`SHARE` of the load cases' static
discrepancy against the reference, together, ``sum_j sum |u*_j - u_ref_j| / sum_j sum |u*_j|``,
the same for every case: the settled cost (paper Eq. 2, a sum over the cases) is within
(1 + SHARE) of the static cost, whatever the lattice's size or the load, and no case is more
than :data:`NOMINAL` (1%) from its static equilibrium. One distance for all, not each case's
own share: a case the model fits closely would otherwise settle the more closely and take the
longest.

The estimate is what the run knows; the damping stage also *measures* the settled state's
distance against the static equilibrium it has solved (:func:`measured_distance`), and the
result reports both per load case.

Where the spec names ``fpm.settle_tolerance`` the force criterion keeps its meaning. It is
also the criterion where there are no modes to read: the paper method's joint (k, d)
annealing (thousands of dynamic runs at trial stiffnesses, none of which has its modes; the
paper's Table 1 is reproduced with it) and a lattice that is a mechanism at rest (``axis``
springs), with :data:`FORCE_TOLERANCE` where the spec names none.
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
