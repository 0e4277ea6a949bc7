"""Spring stiffness: one k for every spring (the paper's) or one k per spring family.

The stiffness parameters of a fit are a vector ``theta`` (N/m):

- ``single``: ``theta = [k]``, every spring gets k (paper Sec. 4.2);
- ``families``: one k per family the connectivity has, in :data:`fpm.model.hexahedron.FAMILIES`
  order (axis = hexahedron edges, face diagonals, body diagonals): ``axis`` 1 value,
  ``axis+face`` 2, ``full`` 3.

On top of either, the spec's per-axis ``stiffness_scale`` (paper Fig. 5) multiplies a spring
along unit vector e by ``sx ex^2 + sy ey^2 + sz ez^2``. :func:`spring_stiffness` turns theta
into the (S,) per-spring stiffness every solver (dynamic and static) works with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .hexahedron import FAMILIES, connectivity_families
from .problem import Problem


def family_names(problem: Problem) -> tuple[str, ...]:
    """Names of the fitted stiffness parameters: ("k",) for single, else the families present."""
    if problem.spec.fpm.stiffness == "single":
        return ("k",)
    g = problem.spec.geometry
    return connectivity_families(getattr(g, "connectivity", "axis"))


def axis_factors(problem: Problem) -> np.ndarray | None:
    """(S,) per-spring factor of the spec's stiffness_scale, or None when it is (1, 1, 1)."""
    scale = np.asarray(problem.spec.fpm.stiffness_scale, dtype=float)
    if np.all(scale == 1.0):
        return None
    cached = problem.cache.get("axis_factors")
    if cached is None:
        s = problem.solid
        e = s.nodes[s.springs[:, 1]] - s.nodes[s.springs[:, 0]]
        e /= problem.rest_lengths[:, None]
        cached = problem.cache["axis_factors"] = (e * e) @ scale
    return cached


def spring_stiffness(problem: Problem, theta: float | Sequence[float] | np.ndarray) -> np.ndarray:
    """(S,) stiffness of every spring, N/m, from the fitted parameters ``theta``.

    Args:
        problem: the problem (its ``fpm.stiffness`` says how theta is read).
        theta: k (a float or one value) for ``single``; one k per family present for
            ``families`` (a single value is also accepted there: every family gets it).
    """
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
    """Theta as {family: k, N/m} for every family present (single: each family gets k)."""
    g = problem.spec.geometry
    present = connectivity_families(getattr(g, "connectivity", "axis"))
    values = list(theta)
    if len(values) == 1:
        values = values * len(present)
    return {name: float(v) for name, v in zip(present, values, strict=True)}


__all__ = ["FAMILIES", "axis_factors", "family_names", "spring_stiffness", "stiffness_dict"]
