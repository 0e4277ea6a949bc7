"""The lattice's parameters for material regions and transversely isotropic materials.

families+volume (:mod:`fpm.model.stiffness`) fits one k per spring family and one kappa. Two
material options multiply or extend that vector theta (docs/physics.md, *Material regions*,
*Transversely isotropic material*):

- **Regions** (``material.regions``, :mod:`fpm.model.regions`): theta holds the families and
  kappa of every region present, base first: ``(axis, face, body, kappa, axis[r1], face[r1],
  body[r1], kappa[r1], ...)``. A cell gives its springs its region's family k times its share
  (:data:`fpm.model.shares.CELL_SHARE`), so a spring on the boundary of two regions gets a
  share from each, as an FEM assembles two materials; a cell carries its region's kappa.
- **Transversely isotropic** (``material.type``, :mod:`fpm.model.anisotropy`): theta ends with
  the axial scale s, and every assembled spring along unit vector e is multiplied by
  ``1 + (s - 1) (e . a)^2`` (the paper's per-axis stiffness_scale, fitted).

Both keep the model linear in its parts at rest, which the reduced linear model of stage 1
needs (:func:`linear_parts`: for the transversely isotropic lattice the parts are each family's
springs across the axis, along it, and the cells, with coefficients ``k``, ``s k`` and kappa).
The homogeneous isotropic model does not come here (:func:`is_extended`), so its numbers are
untouched. A spec with either option fits 'families+volume', with isotropic regions also
'field', a per-cell field on each region's parameters (:func:`fpm.model.stiffness.field_terms`,
:func:`fpm.model.regions.check_material`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import scipy.sparse as sp

from .anisotropy import axial_cosines, closed_form_start, local_stiffness, target_constants
from .forces import Stiffness
from .hexahedron import connectivity_families
from .problem import Problem
from .shares import cell_shares
from .spec import BASE_REGION, lame_constants

VOLUME = "kappa"
"""Name of the volume stiffness among the fitted parameters (as :mod:`fpm.model.stiffness`)."""
AXIAL_SCALE = "axial_scale"
"""Name of the transversely isotropic lattice's axial scale s among the fitted parameters."""
SCALE_SPAN = 10.0
"""The fit searches the axial scale within this factor of the closed form's either way."""


def is_extended(problem: Problem) -> bool:
    """The spec has material regions or a transversely isotropic material."""
    return problem.regions is not None or is_transverse(problem)


def is_transverse(problem: Problem) -> bool:
    """The spec's material is transversely isotropic."""
    return problem.spec.material.type == "transversely-isotropic"


def families(problem: Problem) -> tuple[str, ...]:
    """The spring families present (axis, face, body)."""
    return connectivity_families(getattr(problem.spec.geometry, "connectivity", "axis"))


def region_names(problem: Problem) -> tuple[str, ...]:
    """The regions present, base first (one, ``"base"``, without regions)."""
    return problem.regions.names if problem.regions is not None else (BASE_REGION,)


def suffix(region: str) -> str:
    """What a region's parameter names carry: nothing for the base, ``[name]`` otherwise."""
    return "" if region == BASE_REGION else f"[{region}]"


def parameter_names(problem: Problem) -> tuple[str, ...]:
    """The fitted parameters' names: each region's families and kappa (the base's bare, the
    others' with ``[name]``), then ``axial_scale`` for a transversely isotropic material."""
    base = (*families(problem), VOLUME)
    names = [f"{n}{suffix(r)}" for r in region_names(problem) for n in base]
    return (*names, AXIAL_SCALE) if is_transverse(problem) else tuple(names)


def _per_region(problem: Problem, values: np.ndarray) -> tuple[np.ndarray, float | None]:
    """theta as (R, F + 1) rows of families and kappa per region, and the axial scale."""
    n = len(families(problem)) + 1
    r = len(region_names(problem))
    scale = float(values[-1]) if is_transverse(problem) else None
    return values[: r * n].reshape(r, n), scale


def region_weights(problem: Problem) -> np.ndarray:
    """(R, S) per region (:func:`region_names` order) and spring, the sum over the region's
    cells that contain the spring of the share they give it (:func:`fpm.model.shares.cell_shares`
    times each region's indicator over the cells): the rows add up to
    :func:`fpm.model.stiffness.assembly_weights`. Kept in the problem's cache."""
    cached = problem.cache.region_weights
    if cached is None:
        shares = cell_shares(problem)
        count = len(region_names(problem))
        cells = (
            problem.regions.cells
            if problem.regions is not None
            else np.zeros(shares.shape[1], dtype=np.int64)
        )
        indicator = sp.csr_matrix(
            (np.ones(len(cells)), (np.arange(len(cells)), cells)), shape=(len(cells), count)
        )
        # Sums of 1/4, 1/2 and 1: exact in any order.
        cached = problem.cache.region_weights = (shares @ indicator).T.toarray()
    return cached


def spring_axial_cosines(problem: Problem) -> np.ndarray:
    """(S,) ``(e . a)^2`` of every spring's rest direction e and the material axis a."""
    cached = problem.cache.axial_cosines
    if cached is None:
        s = problem.solid
        e = (s.nodes[s.springs[:, 1]] - s.nodes[s.springs[:, 0]]) / problem.rest_lengths[:, None]
        axis = getattr(problem.spec.material, "axis", (0.0, 0.0, 1.0))
        cached = problem.cache.axial_cosines = axial_cosines(e, axis)
    return cached


def stiffness(problem: Problem, values: np.ndarray, factor: np.ndarray | None) -> Stiffness:
    """The :class:`~fpm.model.forces.Stiffness` of ``values`` (theta, :func:`parameter_names`
    order): springs assembled region by region, times the axial factor and the spec's
    stiffness_scale ``factor`` (S,) if any; every cell its region's kappa."""
    rows, scale = _per_region(problem, values)
    weights = region_weights(problem)
    kinds = problem.solid.families
    springs = np.zeros(weights.shape[1])
    for r, row in enumerate(rows):
        springs += row[:-1][kinds] * weights[r]
    if scale is not None:
        springs = springs * (1.0 + (scale - 1.0) * spring_axial_cosines(problem))
    if factor is not None:
        springs = springs * factor
    n_cells = len(problem.solid.elements())  # type: ignore[arg-type]
    if problem.regions is None:
        volume = np.full(n_cells, rows[0, -1])
    else:
        volume = rows[:, -1][problem.regions.cells]
    return Stiffness(springs, volume)


def linear_parts(
    problem: Problem, factor: np.ndarray | None
) -> tuple[list[Stiffness], Callable[[np.ndarray], np.ndarray]]:
    """The model at rest as ``sum_p c_p(theta) part_p``: the parts (each a Stiffness) and the
    coefficients c(theta). Regions: one part per parameter, c = theta. Transversely isotropic:
    per region and family its springs' part across the axis (``1 - (e . a)^2``) and along it
    (``(e . a)^2``), with c = k and s k, then kappa."""
    n = len(parameter_names(problem))
    if not is_transverse(problem):
        eye = np.eye(n)
        return [stiffness(problem, eye[p], factor) for p in range(n)], lambda t: t
    weights = region_weights(problem)
    cos2 = spring_axial_cosines(problem)
    kinds = problem.solid.families
    f = len(families(problem))
    n_cells = len(problem.solid.elements())  # type: ignore[arg-type]
    cells = (
        problem.regions.cells if problem.regions is not None else np.zeros(n_cells, dtype=np.int32)
    )
    no_cells = np.zeros(n_cells)
    spring_parts: list[Stiffness] = []
    axial_parts: list[Stiffness] = []
    volume_parts: list[Stiffness] = []
    for r in range(len(weights)):
        for family in range(f):
            assembled = np.where(kinds == family, weights[r], 0.0)
            if factor is not None:
                assembled = assembled * factor
            spring_parts.append(Stiffness(assembled * (1.0 - cos2), no_cells))
            axial_parts.append(Stiffness(assembled * cos2, no_cells))
        volume_parts.append(Stiffness(np.zeros(len(kinds)), (cells == r).astype(float)))

    def coefficients(theta: np.ndarray) -> np.ndarray:
        rows, scale = _per_region(problem, np.asarray(theta, dtype=float))
        k = rows[:, :-1].ravel()
        return np.concatenate([k, float(scale) * k, rows[:, -1]])  # type: ignore[arg-type]

    return spring_parts + axial_parts + volume_parts, coefficients


def start(problem: Problem, floor: float) -> list[float]:
    """The fit's start: per region the continuum start of its material (k1 = k2 = mu h,
    k3 = floor mu h, kappa = lambda - mu, at least floor mu); for a transversely isotropic
    material the closed form of :func:`fpm.model.anisotropy.closed_form_start` and its s."""
    h = problem.spacing  # the cell size (fpm.model.problem.Problem.spacing)
    f = len(families(problem))
    if is_transverse(problem):
        material = problem.spec.material
        mu = _shear_floor_scale(problem)
        k, kappa, scale, _ = closed_form_start(material, h, f, floor * mu)
        return [*k, kappa, scale]
    theta: list[float] = []
    for e, nu, _ in _materials(problem):
        mu, lam = lame_constants(e, nu)
        theta += [mu * h, mu * h, floor * mu * h][:f] + [max(lam - mu, floor * mu)]
    return theta


def _materials(problem: Problem) -> tuple[tuple[float, float, float], ...]:
    if problem.regions is not None:
        return problem.regions.materials
    m = problem.spec.material
    return ((m.youngs_modulus, m.poisson_ratio, m.density),)


def _shear_floor_scale(problem: Problem) -> float:
    """The smaller shear modulus of a transversely isotropic material, Pa (the scale of the
    floors, as mu is for an isotropic one)."""
    c = target_constants(local_stiffness(problem.spec.material))
    return float(min(c[4], c[5]))


def bounds(
    problem: Problem, k: tuple[float, float] | None, floor: float
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) per parameter, as :func:`fpm.fitting.bounds.stiffness_bounds` gives the
    homogeneous model, per region from its own material: each family from floor mu h (or the
    spec's lower k bound if lower) to the top of the k bounds (the spec's ``k``, else 10 E h),
    kappa in [floor mu, 10 (lambda + 2 mu)]. Transversely isotropic: mu the smaller shear
    modulus, E the transverse modulus, kappa up to 10 times the largest normal stiffness, and
    the axial scale within :data:`SCALE_SPAN` of the closed form's."""
    h = problem.spacing  # the cell size (fpm.model.problem.Problem.spacing)
    f = len(families(problem))
    lower: list[float] = []
    upper: list[float] = []
    if is_transverse(problem):
        material = problem.spec.material
        mu = _shear_floor_scale(problem)
        ks = k or (material.youngs_modulus * h / 100, 10 * material.youngs_modulus * h)
        c = target_constants(local_stiffness(material))
        scale = start(problem, floor)[-1]
        lower = [min(ks[0], floor * mu * h)] * f + [floor * mu, scale / SCALE_SPAN]
        upper = [ks[1]] * f + [10 * float(max(c[0], c[1])), scale * SCALE_SPAN]
        return np.asarray(lower), np.asarray(upper)
    for e, nu, _ in _materials(problem):
        mu, lam = lame_constants(e, nu)
        ks = k or (e * h / 100, 10 * e * h)
        lower += [min(float(ks[0]), floor * mu * h)] * f + [floor * mu]
        upper += [float(ks[1])] * f + [10 * (lam + 2 * mu)]
    return np.asarray(lower), np.asarray(upper)


def notes(problem: Problem) -> list[str]:
    """A region below Poisson's ratio 1/4 (its kappa held at the floor), as
    :func:`fpm.fitting.bounds.mode_notes` says of the homogeneous model."""
    if is_transverse(problem):
        return []
    found = []
    for name, (e, nu, _) in zip(region_names(problem), _materials(problem), strict=True):
        mu, lam = lame_constants(e, nu)
        if lam < mu:
            found.append(
                f"region {name}: Poisson's ratio {nu:g} < 1/4: its kappa is held at its floor, "
                "so it stays near nu = 1/4 (as the spring-only models)"
            )
    return found


def stiffness_values(problem: Problem, theta: Any) -> dict[str, float]:
    """The result's ``stiffness``: every parameter by name but the base's kappa (that is
    ``volume_stiffness``): the base's families, each other region's families and kappa
    (``kappa[name]``, Pa), and ``axial_scale``."""
    names = parameter_names(problem)
    return {n: float(v) for n, v in zip(names, theta, strict=True) if n != VOLUME}


def base_kappa(problem: Problem, theta: Any) -> float | None:
    """The base region's kappa, Pa (None when every cell is in another region)."""
    names = parameter_names(problem)
    return float(theta[names.index(VOLUME)]) if VOLUME in names else None


def theta_from(problem: Problem, stiffness: Mapping[str, Any] | None, kappa: Any) -> list[float]:
    """theta from a record's ``stiffness`` (by name, :func:`stiffness_values`) and
    ``volume_stiffness`` (the base's kappa).

    Raises:
        ValueError: a parameter is missing (the record names which).
    """
    stiffness = stiffness or {}
    theta: list[float] = []
    missing: list[str] = []
    for name in parameter_names(problem):
        value = kappa if name == VOLUME else stiffness.get(name)
        if value is None:
            missing.append(name)
        else:
            theta.append(float(value))
    if missing:
        raise ValueError(
            f"the parameters lack {', '.join(missing)} (material regions and transversely "
            "isotropic materials keep every region's parameters by name in 'stiffness', the "
            "base's kappa in 'volume_stiffness'): use the spec they were fitted on"
        )
    return theta


def report(problem: Problem, theta: Any) -> list[dict[str, Any]] | None:
    """The result's ``regions``: per region present its name, cells, material and fitted
    families (N/m) and kappa (Pa); None without regions."""
    regions = problem.regions
    if regions is None:
        return None
    rows, _ = _per_region(problem, np.asarray(theta, dtype=float))
    names = families(problem)
    return [
        {
            "name": name,
            "cells": count,
            "youngs_modulus": material[0],
            "poisson_ratio": material[1],
            "density": material[2],
            "stiffness": {n: float(v) for n, v in zip(names, row[:-1], strict=True)},
            "volume_stiffness": float(row[-1]),
        }
        for name, count, material, row in zip(
            regions.names, regions.counts, regions.materials, rows, strict=True
        )
    ]
