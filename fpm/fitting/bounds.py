"""The calibration's search box: the ranges of the stiffness parameters, of d and of the depth.

- stiffness (:func:`stiffness_bounds`), the same for every spring family: the spec's
  ``annealing.bounds.k``, else [E h / 100, 10 E h] N/m (a lattice of cells of size h has an
  effective modulus of order k/h; h is :attr:`fpm.model.problem.Problem.spacing`, the shortest
  spring on a regular lattice, the cells' typical size on one conformed to a surface);
  families+volume: each family from FLOOR mu h (its 'zero') to the top of the k bounds, and
  kappa in [FLOOR mu, 10 (lambda + 2 mu)] Pa;
- d (:func:`damping_bounds`): the spec's ``annealing.bounds.d``, else [0.1, 5] sqrt(E h m) N s/m,
  m the mean node mass: sqrt(k m) is the damping scale of a node on springs of stiffness k ~ E h;
- depth, layers of the perturbed list: the chains fit at the spec's integer depth, or at every
  layer for 'full' and 'auto' (:func:`fit_depth`); :func:`full_depth` is the deepest list over
  the load cases, the top of the search for depth 'auto'.

:func:`mode_notes` tells the user what the kappa bound means below Poisson's ratio 1/4.

The cost (the paper method's dt at the top of the stiffness bounds,
:func:`fpm.fitting.cost.dynamic_time_step`) and both calibration stages import this module; it
imports no other module of fpm.fitting.
"""

from __future__ import annotations

import numpy as np

from ..dynamics.simulation import fpm_model
from ..model import materials
from ..model.materials import is_extended
from ..model.problem import Problem
from ..model.spec import lame_constants
from ..model.stiffness import FLOOR, family_names, has_volume


def stiffness_bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) for the stiffness parameters: the spec's k bounds, else
    [E h / 100, 10 E h] N/m (h: the lattice's cell size, :attr:`Problem.spacing`), the same for
    every family. families+volume: each family from FLOOR mu h (its 'zero') to the top of the
    k bounds, and kappa in [FLOOR mu, 10 (lambda + 2 mu)] Pa (kappa >= 0: for nu < 1/4 it
    stays at its floor, see :func:`fpm.model.stiffness.continuum_start`)."""
    if is_extended(problem):  # per material region, or the transversely isotropic lattice's
        return materials.bounds(problem, problem.spec.annealing.bounds.k, FLOOR)
    eh = problem.spec.material.youngs_modulus * problem.spacing
    k = problem.spec.annealing.bounds.k or (eh / 100, 10 * eh)
    n = len(family_names(problem))
    if not has_volume(problem):
        return np.full(n, float(k[0])), np.full(n, float(k[1]))
    m = problem.spec.material
    mu, lam = lame_constants(m.youngs_modulus, m.poisson_ratio)
    low = min(float(k[0]), FLOOR * mu * problem.spacing)
    lower = np.append(np.full(n - 1, low), FLOOR * mu)
    upper = np.append(np.full(n - 1, float(k[1])), 10 * (lam + 2 * mu))
    return lower, upper


def damping_bounds(problem: Problem) -> tuple[float, float]:
    """(lower, upper) for d, N s/m: the spec's, else [0.1, 5] sqrt(E h m) (h: the cell size,
    :attr:`Problem.spacing`; m: the mean node mass)."""
    eh = problem.spec.material.youngs_modulus * problem.spacing
    scale = float(np.sqrt(eh * problem.solid.masses.mean()))
    d = problem.spec.annealing.bounds.d or (0.1 * scale, 5 * scale)
    return float(d[0]), float(d[1])


def fit_depth(problem: Problem) -> int | None:
    """The depth chains fit at: the spec's integer, or None (every layer) for 'full' and
    'auto'."""
    return problem.spec.fpm.layers


def full_depth(problem: Problem) -> int:
    """The deepest perturbed list over the load cases, layers."""
    model = fpm_model(problem)
    return max(model.perturbed_list(j, None).layers for j in range(len(problem.load_cases)))


def mode_notes(problem: Problem) -> list[str]:
    """What the user should know about the stiffness mode (families+volume below nu 1/4)."""
    if is_extended(problem):
        return materials.notes(problem)
    m = problem.spec.material
    mu, lam = lame_constants(m.youngs_modulus, m.poisson_ratio)
    if has_volume(problem) and lam < mu:
        return [
            f"Poisson's ratio {m.poisson_ratio:g} < 1/4: the volume term would need a negative "
            f"kappa (lambda - mu = {lam - mu:.4g} Pa), which can let cells collapse; kappa is "
            "held at its floor, so the lattice stays near nu = 1/4 (as the spring-only models)"
        ]
    return []
