"""The stiffness field's parameters (:mod:`fpm.fitting.field`): what its fit moves, and the
smoothness penalty over the cells.

The field gives every cell c two factors on the families+volume fit theta (the families' k,
N/m, then kappa, Pa): ``a_c`` on what the cell gives its springs (its share of their family's
k) and ``b_c`` on its kappa (:func:`fpm.model.stiffness.field_stiffness`), fitted in log
space, x = (log a, log b) (:class:`FieldMap`, each within +-:data:`SPAN`). The smoothness
penalty ``P = mean over neighbouring cells (c, d) of (log a_c - log a_d)^2 + (log b_c -
log b_d)^2`` runs over the edges of a cell-adjacency graph (:func:`cell_adjacency`: cells
sharing a face; edges between two regions can be dropped, so a region's field is never
smoothed into its neighbour's). The cross-validation's folds refit the four parameters
themselves, as x = log theta (:class:`FamilyMap`). Either maps x to the model's Stiffness and
pulls gradients by the stiffnesses back to gradients by x (:mod:`fpm.fitting.adjoint`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from ..model.forces import Stiffness
from ..model.hexahedron import NATURAL
from ..model.problem import Problem
from ..model.shares import cell_shares
from ..model.stiffness import (
    axis_factors,
    field_stiffness,
    field_terms,
    linear_parts,
    model_stiffness,
)
from .bounds import stiffness_bounds

SPAN = math.log(10.0)
"""Each log factor stays within +-this (a cell's springs or kappa at most 10x up or down)."""


def cell_adjacency(hexahedra: np.ndarray, regions: np.ndarray | None = None) -> np.ndarray:
    """(E, 2) the pairs of cells (indices into ``hexahedra`` (H, 8)) that share a face, each
    once, smaller index first: the graph the smoothness penalty runs over. ``regions``: (H,)
    a label per cell; pairs whose labels differ are dropped, so a region's field is smoothed
    within the region only (material regions refine their own parameters)."""
    faces = [np.flatnonzero(NATURAL[:, axis] == side) for axis in range(3) for side in (-1, 1)]
    quads = np.sort(np.concatenate([hexahedra[:, f] for f in faces]), axis=1)  # (6H, 4)
    owner = np.tile(np.arange(len(hexahedra)), len(faces))
    _, inverse, counts = np.unique(quads, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    shared = counts[inverse] == 2
    order = np.argsort(inverse[shared], kind="stable")
    pairs = owner[shared][order].reshape(-1, 2)
    pairs = np.sort(pairs, axis=1)
    if regions is not None:
        labels = np.asarray(regions)
        pairs = pairs[labels[pairs[:, 0]] == labels[pairs[:, 1]]]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


class FieldMap:
    """The field's parameters x = (log a, log b) (2H,) -> the model's Stiffness at theta, and
    gradients by the stiffnesses back to gradients by x; the smoothness penalty over ``edges``
    (:func:`cell_adjacency`). With material regions a cell's factors multiply its own
    region's parameters (:func:`fpm.model.stiffness.field_terms`)."""

    def __init__(self, problem: Problem, theta: Sequence[float], edges: np.ndarray):
        self.problem = problem
        self.theta = [float(t) for t in theta]
        self.shares = cell_shares(problem)
        self.cells = self.shares.shape[1]
        # k_s = sum_r k[r, s] sum_(c in r) share_sc a_c (times the spec's stiffness_scale)
        k, self.kappa, self.region = field_terms(problem, self.theta)
        factor = axis_factors(problem)
        self.family_k = k if factor is None else k * factor
        self.kappa_cell = self.kappa[self.region]
        n = len(edges)
        rows = np.repeat(np.arange(n), 2)
        values = np.tile([1.0, -1.0], n)
        self.difference = sp.csr_matrix(
            (values, (rows, np.asarray(edges).ravel())), shape=(n, self.cells)
        )
        self.edges = n

    @property
    def size(self) -> int:
        return 2 * self.cells

    def bounds(self) -> list[tuple[float, float]]:
        return [(-SPAN, SPAN)] * self.size

    def factors(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(spring factors (H,), kappa factors (H,)) at x."""
        return np.exp(x[: self.cells]), np.exp(x[self.cells :])

    def stiffness(self, x: np.ndarray) -> Stiffness:
        return field_stiffness(self.problem, self.theta, *self.factors(x))

    def pull_back(self, x: np.ndarray, springs: np.ndarray, kappa: np.ndarray) -> np.ndarray:
        """dcost/dx from dcost/dk_s (S,) and dcost/dkappa_c (H,)."""
        a, b = self.factors(x)
        by_a = np.zeros(self.cells)
        for r, k in enumerate(self.family_k):
            part = self.shares.T @ (k * springs)
            by_a += part if len(self.family_k) == 1 else np.where(self.region == r, part, 0.0)
        return np.concatenate([a * by_a, self.kappa_cell * b * kappa])

    def smoothness(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """P(x), the mean squared log-factor step over the edges, and its gradient."""
        if not self.edges:
            return 0.0, np.zeros(self.size)
        d = self.difference
        steps = [d @ x[: self.cells], d @ x[self.cells :]]
        value = float(sum(s @ s for s in steps)) / self.edges
        grad = np.concatenate([2.0 * (d.T @ s) for s in steps]) / self.edges
        return value, grad


class FamilyMap:
    """The families+volume parameters (with material regions each region's) as x = log theta
    -> Stiffness, and the gradient by x from the stiffnesses': the model is linear in theta,
    ``sum_p theta_p part_p`` (:func:`fpm.model.stiffness.linear_parts`)."""

    def __init__(self, problem: Problem):
        self.problem = problem
        lower, upper = stiffness_bounds(problem)
        self._bounds = list(zip(np.log(lower), np.log(upper), strict=True))
        self.size = len(lower)
        self.parts, _ = linear_parts(problem)  # c(theta) = theta: no axial scale (field_terms)

    def bounds(self) -> list[tuple[float, float]]:
        return self._bounds

    def stiffness(self, x: np.ndarray) -> Stiffness:
        return model_stiffness(self.problem, np.exp(x))

    def pull_back(self, x: np.ndarray, springs: np.ndarray, kappa: np.ndarray) -> np.ndarray:
        theta = np.exp(x)
        return np.array(
            [
                t * (part.springs @ springs + part.volume @ kappa)
                for t, part in zip(theta, self.parts, strict=True)
            ]  # type: ignore[operator]
        )

    def smoothness(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        return 0.0, np.zeros(self.size)


Parameters = FieldMap | FamilyMap
