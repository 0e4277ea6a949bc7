"""The stiffness modes: from the fitted parameters theta to the model's :class:`Stiffness`.

The stiffness parameters of a fit are a vector ``theta``:

- ``single``: ``theta = [k]`` (N/m), every spring gets k (the paper's model, Sec. 4.2);
- ``families``: one k (N/m) per family the connectivity has, in
  :data:`fpm.model.hexahedron.FAMILIES` order (axis = hexahedron edges, face diagonals, body
  diagonals): ``axis`` 1 value, ``axis+face`` 2, ``full`` 3;
- ``families+volume`` (the default): the family stiffnesses (N/m) and then kappa (Pa), the
  volume stiffness of every cell (:mod:`fpm.model.volume`). Here springs are *assembled from
  cells*: each cell gives its 12 edges, 12 face diagonals and 4 body diagonals 1/4, 1/2 and 1
  of their family's k, so an interior spring gets k and a surface one less, as in an FEM's
  assembly (:func:`assembly_weights`). Its continuum limit is the isotropic solid
  ``C11 = (k1 + 2 k2 + 4 k3 / 3) / h + kappa``, ``C12 = (k2 + 4 k3 / 3) / h + kappa``,
  ``C44 = (k2 + 4 k3 / 3) / h``, so :func:`continuum_start` (``k1 = k2 = mu h``, ``k3 = 0``,
  ``kappa = lambda - mu``) matches the material's Lame constants exactly in the lattice's
  interior; the fit corrects the boundary and the discretisation.
- ``field``: the same theta, and on top a per-cell factor on what each cell gives its springs
  and one on its kappa (:func:`field_stiffness`; fitted by :mod:`fpm.fitting.field`).

On top of any mode, the spec's per-axis ``stiffness_scale`` (paper Fig. 5) multiplies a spring
along unit vector e by ``sx ex^2 + sy ey^2 + sz ez^2``. :func:`model_stiffness` turns theta
into the :class:`fpm.model.forces.Stiffness` every solver (dynamic and static) works with
(a Stiffness given in theta's place is taken as it is); :func:`spring_stiffness` is its (S,)
spring part.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from . import materials
from .forces import Stiffness
from .hexahedron import connectivity_families
from .materials import is_extended
from .problem import Problem
from .shares import cell_shares
from .spec import VOLUME_MODES, lame_constants

VOLUME = "kappa"
"""Name of the volume stiffness among the fitted parameters (Pa)."""

FLOOR = 1e-3
"""families+volume: the smallest body-diagonal stiffness (times mu h) and volume stiffness
(times mu) a fit considers; 'zero' in a log-space search."""


def family_names(problem: Problem) -> tuple[str, ...]:
    """Names of the fitted stiffness parameters: ("k",) for single, the families present for
    families, and then "kappa" for families+volume (and field)."""
    mode = problem.spec.fpm.stiffness
    if mode == "single":
        return ("k",)
    if is_extended(problem):  # material regions, transversely isotropic (fpm.model.materials)
        return materials.parameter_names(problem)
    g = problem.spec.geometry
    names = connectivity_families(getattr(g, "connectivity", "axis"))
    return (*names, VOLUME) if mode in VOLUME_MODES else names


def has_volume(problem: Problem) -> bool:
    """The spec's stiffness mode carries the volume term."""
    return problem.spec.fpm.stiffness in VOLUME_MODES


def is_field(problem: Problem) -> bool:
    """The spec fits a per-cell stiffness field (``fpm.stiffness: "field"``)."""
    return problem.spec.fpm.stiffness == "field"


def assembly_weights(problem: Problem) -> np.ndarray:
    """(S,) per spring, the sum over the cells that contain it of the share of its family's k
    that cell gives it (:data:`fpm.model.shares.CELL_SHARE`): 1 for an interior spring of a
    regular lattice, less on the surface."""
    cached = problem.cache.assembly_weights
    if cached is None:
        # Sums of 1/4, 1/2 and 1: exact in any order.
        weights = np.asarray(cell_shares(problem).sum(axis=1)).ravel()
        cached = problem.cache.assembly_weights = weights
    return cached


def continuum_start(problem: Problem) -> list[float]:
    """families+volume: the closed-form parameters whose lattice, in its interior, is the
    material's isotropic solid: k1 = k2 = mu h, k3 = 0, kappa = lambda - mu (N/m, Pa; h the
    cell size, :attr:`fpm.model.problem.Problem.spacing`).

    For nu < 1/4, lambda - mu < 0: a negative volume stiffness could make cells collapse, so
    kappa starts (and stays, see :func:`fpm.fitting.bounds.stiffness_bounds`) at its
    floor, and the lattice cannot go below nu = 1/4 (the families' limit). k3 = 0 cannot be a
    point of a log-space search: it starts at the floor :data:`FLOOR` times mu h.

    Material regions: each region's own; transversely isotropic: the closed form nearest the
    stiffness tensor, with its axial scale (:func:`fpm.model.materials.start`).
    """
    if is_extended(problem):
        return materials.start(problem, FLOOR)
    m = problem.spec.material
    mu, lam = lame_constants(m.youngs_modulus, m.poisson_ratio)
    h = problem.spacing
    names = family_names(problem)
    k = [mu * h, mu * h, FLOOR * mu * h][: len(names) - 1]
    return [*k, max(lam - mu, FLOOR * mu)]


def axis_factors(problem: Problem) -> np.ndarray | None:
    """(S,) per-spring factor of the spec's stiffness_scale, or None when it is (1, 1, 1)."""
    scale = np.asarray(problem.spec.fpm.stiffness_scale, dtype=float)
    if np.all(scale == 1.0):
        return None
    cached = problem.cache.axis_factors
    if cached is None:
        s = problem.solid
        e = s.nodes[s.springs[:, 1]] - s.nodes[s.springs[:, 0]]
        e /= problem.rest_lengths[:, None]
        cached = problem.cache.axis_factors = (e * e) @ scale
    return cached


def model_stiffness(
    problem: Problem, theta: float | Sequence[float] | np.ndarray | Stiffness
) -> Stiffness:
    """The model's :class:`~fpm.model.forces.Stiffness` from the fitted parameters ``theta``
    (as :func:`spring_stiffness` reads them; for families+volume the last value is kappa, Pa,
    given to every cell). A Stiffness (e.g. a field's, :func:`field_stiffness`) is returned
    as it is."""
    if isinstance(theta, Stiffness):
        return theta
    if not has_volume(problem):
        return Stiffness(spring_stiffness(problem, theta))
    values = np.atleast_1d(np.asarray(theta, dtype=float))
    names = family_names(problem)
    if len(values) != len(names):
        raise ValueError(
            f"this spec fits {', '.join(names)} (fpm.stiffness 'families+volume'): give "
            f"{len(names)} values, not {len(values)}"
        )
    if is_extended(problem):
        return materials.stiffness(problem, values, axis_factors(problem))
    springs = values[:-1][problem.solid.families] * assembly_weights(problem)
    factor = axis_factors(problem)
    if factor is not None:
        springs = springs * factor
    n_cells = len(problem.solid.elements())  # type: ignore[arg-type]
    return Stiffness(springs, np.full(n_cells, values[-1]))


def field_terms(
    problem: Problem, theta: Sequence[float] | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the ``field`` model multiplies, from theta as families+volume reads it (the
    families' k, N/m, then kappa, Pa; with material regions each region's, base first):
    ``(k, kappa, cells)``, k (R, S) per region the family k of every spring, N/m, kappa (R,)
    each region's, Pa, cells (H,) each cell's region (R = 1 without regions).

    Raises:
        ValueError: theta does not fit the model, or the model has no field (no volume
            term, or a transversely isotropic material, whose axial scale the field has not).
    """
    values = np.atleast_1d(np.asarray(theta, dtype=float))
    names = family_names(problem)
    if not has_volume(problem) or len(values) != len(names) or materials.is_transverse(problem):
        raise ValueError(
            f"a stiffness field needs the families and kappa ({', '.join(names)}) of an "
            "isotropic model with the volume term"
        )
    rows = values.reshape(-1, len(materials.families(problem)) + 1)
    n_cells = cell_shares(problem).shape[1]
    cells = (
        problem.regions.cells if problem.regions is not None else np.zeros(n_cells, dtype=np.int64)
    )
    return rows[:, :-1][:, problem.solid.families], rows[:, -1].copy(), np.asarray(cells)


def field_stiffness(
    problem: Problem,
    theta: Sequence[float] | np.ndarray,
    spring_factor: Sequence[float] | np.ndarray,
    kappa_factor: Sequence[float] | np.ndarray,
) -> Stiffness:
    """The ``field`` model's :class:`~fpm.model.forces.Stiffness`: theta as families+volume
    reads it (:func:`field_terms`: the families' k, N/m, then kappa, Pa, per material region),
    each cell c giving its springs ``spring_factor[c]`` times its share of their family's k
    in its region and carrying ``kappa_factor[c]`` times its region's kappa (both (H,),
    aligned with the hexahedra). With every factor 1 it is :func:`model_stiffness` at theta.

    Raises:
        ValueError: theta or the factors do not fit the lattice, or a factor is not > 0.
    """
    k, kappa, cells = field_terms(problem, theta)
    shares = cell_shares(problem)
    a = np.asarray(spring_factor, dtype=float)
    b = np.asarray(kappa_factor, dtype=float)
    if a.shape != (shares.shape[1],) or b.shape != (shares.shape[1],):
        raise ValueError(
            f"a stiffness field needs one spring factor and one kappa factor per cell "
            f"({shares.shape[1]}), not {a.shape} and {b.shape}"
        )
    if not (np.all(a > 0) and np.all(b > 0)):
        raise ValueError("every factor of a stiffness field must be > 0")
    if len(k) == 1:
        springs = k[0] * (shares @ a)
    else:
        springs = sum(k[r] * (shares @ np.where(cells == r, a, 0.0)) for r in range(len(k)))
    factor = axis_factors(problem)
    if factor is not None:
        springs = springs * factor
    return Stiffness(springs, kappa[cells] * b)


def spring_stiffness(problem: Problem, theta: float | Sequence[float] | np.ndarray) -> np.ndarray:
    """(S,) stiffness of every spring, N/m, from the fitted parameters ``theta``.

    Args:
        problem: the problem (its ``fpm.stiffness`` says how theta is read).
        theta: k (a float or one value) for ``single``; one k per family present for
            ``families`` (a single value is also accepted there: every family gets it); for
            ``families+volume`` the families then kappa (:func:`model_stiffness`).
    """
    if has_volume(problem):
        return model_stiffness(problem, theta).springs
    values = np.atleast_1d(np.asarray(theta, dtype=float))
    families = problem.solid.families
    if len(values) > 1 and problem.spec.fpm.stiffness == "single":
        raise ValueError(
            f"this spec fits one k (fpm.stiffness 'single'): give one value, not {len(values)}"
        )
    if len(values) == 1:
        k = np.full(len(families), values[0])
    else:
        names = family_names(problem)
        if len(values) != len(names):
            raise ValueError(
                f"this spec fits one k per spring family ({', '.join(names)}): give "
                f"{len(names)} values, or one for all"
            )
        k = values[families]
    factor = axis_factors(problem)
    return k if factor is None else k * factor


def stiffness_dict(problem: Problem, theta: Sequence[float]) -> dict[str, float]:
    """Theta as {family: k, N/m} for every family present (single: each family gets k); the
    volume stiffness (families+volume) is not a spring's and is left out (see
    :func:`volume_stiffness`). Material regions and a transversely isotropic material: every
    parameter by name but the base's kappa (:func:`fpm.model.materials.stiffness_values`)."""
    if is_extended(problem):
        return materials.stiffness_values(problem, theta)
    g = problem.spec.geometry
    present = connectivity_families(getattr(g, "connectivity", "axis"))
    values = list(theta)[: len(present)] if has_volume(problem) else list(theta)
    if len(values) == 1:
        values = values * len(present)
    return {name: float(v) for name, v in zip(present, values, strict=True)}


def theta_of(
    problem: Problem, k: float, stiffness: dict[str, float] | None, kappa: float | None
) -> list[float]:
    """The fitted parameters as :func:`model_stiffness` reads them, from what a result or a
    parameter set holds: ``k`` (N/m), ``stiffness`` ({family: k}, N/m) and ``kappa`` (Pa).

    Raises:
        ValueError: the record lacks what the spec's mode needs (a family, or kappa).
    """
    if is_extended(problem):  # every parameter by name (fpm.model.materials.theta_from)
        return materials.theta_from(problem, stiffness, kappa)
    names = family_names(problem)
    if names == ("k",):
        return [float(k)]
    families = [n for n in names if n != VOLUME]
    if stiffness is None or any(n not in stiffness for n in families):
        raise ValueError(f"the parameters lack the stiffness of {', '.join(families)}")
    theta = [float(stiffness[n]) for n in families]
    if has_volume(problem):
        if kappa is None:
            raise ValueError("the parameters lack the volume stiffness kappa (families+volume)")
        theta.append(float(kappa))
    return theta


def fitted_theta(problem: Problem, record: Any) -> list[float] | Stiffness:
    """The parameters :func:`fpm.simulate` and :func:`model_stiffness` take (theta), from a fit's
    record: a stored calibration result or a parameter set as a dict, or an object with these
    attributes (a result's ``parameters``, a parameter set record): ``k``, N/m; ``stiffness``,
    {family: k}, N/m; ``volume_stiffness``, Pa; ``field``, a field fit's per-cell factors. The
    one place a stored fit becomes solver input (the plot, the exports and the worker's views
    all call it).

    ``single``: ``[k]`` (``k`` or the one value every family holds); the other modes:
    :func:`theta_of`; a record whose ``field`` was returned (``fpm.stiffness: "field"``): the
    :class:`~fpm.model.forces.Stiffness` of :func:`field_stiffness`, every spring's and every
    cell's own (a field the fit refused leaves the families+volume theta).

    Raises:
        ValueError: the record lacks what the spec's mode needs, or holds one k per family for a
            spec that fits one k, or a field that does not fit the lattice.
    """
    names = ("k", "stiffness", "volume_stiffness", "field")
    if isinstance(record, Mapping):
        k, stiffness, kappa, field = (record.get(n) for n in names)
    else:
        k, stiffness, kappa, field = (getattr(record, n, None) for n in names)
    if family_names(problem) != ("k",):
        theta = theta_of(problem, 0.0 if k is None else float(k), stiffness, kappa)
        factors = _returned_field(field)
        if factors is None:
            return theta
        if not is_field(problem):
            raise ValueError(
                "the parameters hold a stiffness field but the spec's fpm.stiffness is "
                f"{problem.spec.fpm.stiffness!r}: use the spec they were fitted on"
            )
        return field_stiffness(problem, theta, *factors)
    values = {float(v) for v in stiffness.values()} if isinstance(stiffness, Mapping) else set()
    if len(values) > 1:
        raise ValueError(
            "the parameters hold one k per family but the spec fits one k (fpm.stiffness "
            "'single'): use the spec they were fitted on"
        )
    if k is None and not values:
        raise ValueError("the parameters lack the stiffness k")
    return [float(k) if k is not None else values.pop()]


def _returned_field(field: Any) -> tuple[Any, Any] | None:
    """(spring factors, kappa factors) per cell of a record's field when the fit returned it,
    else None (no field, or one refused in favour of the four-parameter fit)."""
    if field is None:
        return None
    if not isinstance(field, Mapping):
        field = {n: getattr(field, n, None) for n in ("returned", "spring_factor", "kappa_factor")}
    if not field.get("returned"):
        return None
    if field.get("spring_factor") is None or field.get("kappa_factor") is None:
        raise ValueError("the parameters' stiffness field lacks its per-cell factors")
    return field["spring_factor"], field["kappa_factor"]


def volume_stiffness(problem: Problem, theta: Sequence[float]) -> float | None:
    """kappa, Pa, for families+volume (theta's last value; with material regions the base's);
    None for the other modes."""
    if is_extended(problem):
        return materials.base_kappa(problem, theta)
    return float(theta[-1]) if has_volume(problem) else None


def linear_parts(
    problem: Problem,
) -> tuple[list[Stiffness], Callable[[np.ndarray], np.ndarray]]:
    """The model at rest as ``sum_p c_p(theta) part_p`` (what stage 1's reduced linear model
    assembles, :mod:`fpm.fitting.reduced`): the parts and the coefficients c(theta). For the
    modes here one part per parameter, ``model_stiffness`` at its unit vector, and c = theta;
    a transversely isotropic lattice, whose axial scale multiplies the families, has more
    (:func:`fpm.model.materials.linear_parts`)."""
    if is_extended(problem):
        return materials.linear_parts(problem, axis_factors(problem))
    n = len(family_names(problem))
    eye = np.eye(n)
    return [model_stiffness(problem, eye[p]) for p in range(n)], lambda theta: theta
