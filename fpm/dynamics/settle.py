"""When a dynamic run has settled: near its static equilibrium, at every lattice size
(docs/explanation/physics/settle.md).

A run of one load case stops once it is settled. Near the static equilibrium x* of its list,
with K the free nodes' tangent (SPD) and r the unbalanced force (N), the error is
``x - x* = -K^-1 r``. A criterion on the force alone ("largest |r_i| below a tolerance times
the largest applied force", the paper's and the project's first) is not scale-free: K's
lowest eigenvalues fall like h^2 as the lattice is refined, so the same force tolerance lets
the state sit further from rest on a finer lattice (measured on the soft organ with 1e-5:
settled cost / static cost 0.995 at 4.7k nodes, 1.32 at 19.7k, 6.0 at 93.7k).

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
many times the typical one, so a distance relative to the peak let the state sit 25% above the
static cost on the 4.6k-node organ while its peak was 0.1% from equilibrium.

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

import numpy as np
import scipy.linalg as sla

from ..model.spec import ProblemSpec

FORCE_TOLERANCE = 1e-5
"""The force criterion's tolerance where the spec names none but the distance criterion has
no modes to read (the paper method; a mechanism): settled when the largest unbalanced nodal
force is below this times the largest applied nodal force (the default before the distance
criterion)."""

PROMISE = 1.0
"""The settled state is promised within this times fpm.settle_distance of its static
equilibrium, measured (the default 0.01: within 1%); the result warns where it is not."""


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
    relative to the equilibrium's: the 2-norms over every node of their difference and of the
    equilibrium's displacements, divided."""
    size = float(np.linalg.norm(static))
    if not size > 0:
        return float("inf")
    return float(np.linalg.norm(settled - static) / size)
