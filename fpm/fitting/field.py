"""``fpm.stiffness: "field"``: a per-cell stiffness field on top of the families+volume fit
(docs/physics.md, *Calibration*, the field).

Four numbers for a whole solid leave the error where one stiffness cannot serve everywhere
(the surface, near the loads, the fixed boundary). The field gives every cell c two factors on
the families+volume fit theta (the families' k, N/m, then kappa, Pa): ``a_c`` on what the cell
gives its springs (its share of their family's k) and ``b_c`` on its kappa
(:func:`fpm.model.stiffness.field_stiffness`). They are fitted in log space, x = (log a,
log b), by L-BFGS-B on the static equilibria:

    f(x) = sum_j sum_i |p_ij(x) - q_ij| / sum_j sum_i |q_ij|  +  w P(x),

the Eq. (2) cost of the fitted load cases j over all nodes i (p the FPM's equilibrium, q the
reference), normalised, plus a smoothness penalty ``P = mean over neighbouring cells (c, d)
of (log a_c - log a_d)^2 + (log b_c - log b_d)^2`` over the edges of a cell-adjacency graph
(:func:`fpm.fitting.field_parameters.cell_adjacency`: cells sharing a face; edges between two
regions can be dropped, so a region's field is never smoothed into its neighbour's; the
parameters and the penalty: :mod:`fpm.fitting.field_parameters`).

**The gradient, by the adjoint** (:mod:`fpm.fitting.adjoint`): one linear solve per load case
with the exact tangent, whatever the number of parameters, then through the cells' shares to
the factors. tests/core/test_field.py checks it against central differences.

**The smoothness weight, by cross-validation.** Leave one force pattern out at a time
(:func:`load_patterns`: load cases that are scaled copies of one another are one pattern, as
leaving out a scaled copy tests only the force's size): refit the four parameters on the other
cases (:class:`~fpm.fitting.field_parameters.FamilyMap`, the same adjoint), fit the field on
them for each weight of :data:`WEIGHTS` (strongest first, each starting from the last), and
measure the left-out cases (relative discrepancy, %; the mean over the left-out patterns, each
the mean of its cases, :func:`_mean`); where the means at those weights differ by more than
:data:`CV_FLAT`, every fold also fits at the geometric mean of the best two (coarse to fine).
The weight with the smallest mean left-out figure is chosen and the field is fitted on every
load case at it. If even that mean is no better than the four parameters' own left-out mean, or
if every load case is one pattern (nothing to predict), the field is not returned: the
four-parameter fit is, with a warning saying why (:class:`FieldStage`; the field's figures are
still reported beside the four parameters'). The spec's validation cases take no part: they are
measured at the end, for both (:func:`field_report`). The folds run one after another; within
an evaluation the load cases run on threads, each with its own static solver
(:class:`~fpm.fitting.adjoint.Solvers`).

**Material regions.** Each cell's factors multiply its own region's families and kappa, the
folds refit every region's parameters, and the smoothness graph has no edge between two
regions (:func:`fit_field`'s default).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..dynamics.equilibrium import StaticSolver
from ..model.forces import Stiffness
from ..model.problem import Problem, load_patterns
from ..model.stiffness import field_stiffness, model_stiffness
from .adjoint import Objective, Solvers, minimise
from .field_parameters import FamilyMap, FieldMap, cell_adjacency
from .result import FieldFit, ModelFigures

WEIGHTS = (1.0, 0.01)
"""Smoothness weights the cross-validation tries first, strongest first (units: the normalised
cost per mean squared log-factor step between neighbouring cells); where their left-out means
differ by more than :data:`CV_FLAT`, the geometric mean of the best and its neighbour is tried
too (coarse to fine)."""
CV_FLAT = 0.1
"""Left-out means (%, absolute) closer than this are flat: no weight between them is tried."""
CV_ITERATIONS = 10
"""L-BFGS-B iterations of a fold's field fit at one weight (it starts from the last weight's)."""
FINAL_ITERATIONS = 15
"""L-BFGS-B iterations of the field fit on every load case at the chosen weight."""
FOUR_ITERATIONS = 5
"""L-BFGS-B iterations of a fold's refit of the four parameters (from the fit on every case)."""

Progress = Callable[[dict[str, Any]], None]


@dataclass
class FieldStage:
    """The field fit (JSON-able through :meth:`to_dict`).

    Attributes:
        returned: the field is the calibration's model; False: it cross-validated no better
            than the four parameters, which are returned instead (``warning`` says why).
        theta: the families+volume parameters the field multiplies (families' k, N/m; kappa,
            Pa).
        spring_factor, kappa_factor: (H,) the field's factors per cell (aligned with the
            hexahedra), fitted on every load case at the chosen weight.
        weight: the chosen smoothness weight; weights: those tried (strongest first).
        cv_error: per weight, the mean left-out relative discrepancy, %; cv_cases: per weight,
            per left-out load case, %.
        four_cv_error, four_cv_cases: the same for the four parameters refitted without the
            left-out case.
        four_relative, field_relative: per load case, the static relative discrepancy, %, of
            the four-parameter fit and of the field.
        patterns: the load cases grouped by force pattern (:func:`load_patterns`): the
            cross-validation's folds when there are two or more.
        edges: neighbouring cell pairs the smoothness runs over.
        iterations: L-BFGS-B iterations of the final fit; evaluations: adjoint evaluations
            (every fit, the cross-validation's included).
        warning: why the field was not returned ("" when it was).
        seconds: wall time.
    """

    returned: bool
    theta: list[float]
    spring_factor: list[float]
    kappa_factor: list[float]
    weight: float
    weights: list[float]
    cv_error: list[float]
    cv_cases: list[list[float]]
    four_cv_error: float
    four_cv_cases: list[float]
    four_relative: list[float]
    field_relative: list[float]
    patterns: list[list[int]]
    edges: int
    iterations: int
    evaluations: int
    warning: str = ""
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FieldStage:
        return cls(**data)

    def field_stiffness(self, problem: Problem) -> Stiffness:
        """The field's Stiffness (whether or not it was returned)."""
        return field_stiffness(problem, self.theta, self.spring_factor, self.kappa_factor)

    def stiffness(self, problem: Problem) -> Stiffness:
        """The returned model's Stiffness: the field's, or the four parameters'."""
        if self.returned:
            return self.field_stiffness(problem)
        return model_stiffness(problem, self.theta)


def fit_field(
    problem: Problem,
    reference: np.ndarray,
    solver: StaticSolver,
    theta: Sequence[float],
    depth: int | None,
    *,
    weights: Sequence[float] = WEIGHTS,
    iterations: tuple[int, int, int] = (FOUR_ITERATIONS, CV_ITERATIONS, FINAL_ITERATIONS),
    progress: Progress | None = None,
) -> FieldStage:
    """The field on top of the families+volume fit ``theta``, its smoothness weight chosen by
    cross-validation (this module's docstring), at ``depth``. With a single force pattern the
    folds leave out one load case at a time to choose the weight, and the four parameters are
    returned (a warning says why).

    Args:
        reference: (L, N, 3) the load cases' reference displacements, m (the validation cases
            are not given: they stay unseen).
        solver: the static solver of the first load case (its hierarchies and warm starts are
            reused); the others get their own.
        iterations: L-BFGS-B iterations of a fold's four-parameter refit, of a fold's field
            fit at one weight, and of the final field fit.

    The smoothness graph is :func:`cell_adjacency` of the hexahedra, cut between material
    regions; the load cases of an evaluation are solved one per core at once (each has its own
    static solver, so the answer does not depend on how many).
    """
    four_iterations, cv_iterations, final_iterations = iterations
    t0 = time.perf_counter()
    cases = list(range(len(problem.load_cases)))
    if len(cases) < 2:
        raise ValueError("a stiffness field needs two load cases or more to cross-validate")
    hexahedra = problem.solid.elements()
    if hexahedra is None:
        raise ValueError("a network geometry has no cells for a stiffness field")
    labels = None if problem.regions is None else problem.regions.cells
    edges = cell_adjacency(hexahedra, labels)
    theta = [float(t) for t in theta]
    patterns = load_patterns(problem)
    folds = patterns if len(patterns) > 1 else [[j] for j in cases]
    family = FamilyMap(problem)
    workers = max(1, min(len(cases), os.cpu_count() or 1))
    solvers = Solvers([solver, *(StaticSolver(problem) for _ in cases[1:])], workers)
    evaluations = 0

    def report(**info: Any) -> None:
        if progress is not None:
            progress({"phase": "field", **info})

    tried: dict[float, np.ndarray] = {}  # weight -> the left-out figure of every case, %
    four_cv = np.full(len(cases), np.nan)
    fields: list[dict[float, np.ndarray]] = [{} for _ in folds]  # per fold, weight -> x
    maps: list[FieldMap] = []  # per fold, the field on its refitted four parameters

    def fit_weight(fold: int, weight: float, start: np.ndarray) -> int:
        """The fold's field at ``weight`` from ``start``, and its left-out figures; returns
        the evaluations."""
        left, fold_map = folds[fold], maps[fold]
        train = [j for j in cases if j not in left]
        report(step="cross-validation", fold=fold, folds=len(folds), weight=weight)
        objective = Objective(solvers, reference, train, depth, fold_map, weight)
        x, _ = minimise(objective, start, cv_iterations)
        fields[fold][weight] = x
        row = tried.setdefault(weight, np.full(len(cases), np.nan))
        row[left] = solvers.relative(reference, left, fold_map.stiffness(x), depth)
        return objective.evaluations

    try:
        for fold, left in enumerate(folds):
            train = [j for j in cases if j not in left]
            report(step="four parameters", fold=fold, folds=len(folds))
            refit = Objective(solvers, reference, train, depth, family)
            y, _ = minimise(refit, np.log(theta), four_iterations)
            evaluations += refit.evaluations
            four_cv[left] = solvers.relative(reference, left, family.stiffness(y), depth)
            maps.append(FieldMap(problem, list(np.exp(y)), edges))
            x = np.zeros(maps[fold].size)
            for weight in weights:
                evaluations += fit_weight(fold, weight, x)
                x = fields[fold][weight]
        means = {w: _mean(row, folds) for w, row in tried.items()}
        order = sorted(weights, key=lambda w: means[w])
        if len(order) > 1 and abs(means[order[1]] - means[order[0]]) > CV_FLAT:
            middle = math.sqrt(order[0] * order[1])
            stronger = max(order[0], order[1])
            for fold in range(len(folds)):
                evaluations += fit_weight(fold, middle, fields[fold][stronger])
        ranked = sorted(tried, reverse=True)  # strongest first
        cv_error = [_mean(tried[w], folds) for w in ranked]
        best = int(np.argmin(cv_error))
        report(step="final", weight=ranked[best])
        whole = FieldMap(problem, theta, edges)
        objective = Objective(solvers, reference, cases, depth, whole, ranked[best])
        x, taken = minimise(objective, np.zeros(whole.size), final_iterations)
        evaluations += objective.evaluations
        four_relative = solvers.relative(reference, cases, model_stiffness(problem, theta), depth)
        field_relative = solvers.relative(reference, cases, whole.stiffness(x), depth)
    finally:
        solvers.close()
    a, b = whole.factors(x)
    four_error = _mean(four_cv, folds)
    field_error = float(cv_error[best])
    returned = len(patterns) > 1 and field_error < four_error
    warning = ""
    if len(patterns) == 1:
        warning = (
            "the stiffness field was not returned: every load case is a scaled copy of one "
            "force pattern, so leaving one out tests only the force's size and nothing shows "
            "how the field does on another load (on the paper's cube it fits its pull better "
            "and other loads worse); the families+volume fit is returned (the field's figures "
            "are in the result's field). Give load cases of different patterns (another point, "
            "another direction) to fit a field"
        )
    elif not returned:
        warning = (
            f"the stiffness field was not returned: left out one force pattern at a time, it "
            f"reached {field_error:.2f}% on average at its best smoothness weight "
            f"({ranked[best]:g}) where the four parameters refitted the same way reach "
            f"{four_error:.2f}%, so the field fits the loads it was given better than it "
            "predicts others (overfitting); the families+volume fit is returned (the field's "
            "figures are in the result's field)"
        )
    return FieldStage(
        returned=bool(returned),
        theta=theta,
        spring_factor=[float(v) for v in a],
        kappa_factor=[float(v) for v in b],
        weight=float(ranked[best]),
        weights=[float(w) for w in ranked],
        cv_error=[float(v) for v in cv_error],
        cv_cases=[[float(v) for v in tried[w]] for w in ranked],
        four_cv_error=four_error,
        four_cv_cases=[float(v) for v in four_cv],
        four_relative=four_relative,
        field_relative=field_relative,
        patterns=patterns,
        edges=int(len(edges)),
        iterations=taken,
        evaluations=evaluations,
        warning=warning,
        seconds=time.perf_counter() - t0,
    )


def _mean(figures: np.ndarray, folds: Sequence[Sequence[int]]) -> float:
    """The mean left-out figure, %, over the ``folds`` (each the mean of its left-out cases'
    ``figures``), inf where a case had no equilibrium. A fold is one force pattern, so a
    pattern given at three sizes counts once, as one given at one size does."""
    if not np.isfinite(figures).all():
        return float("inf")
    return float(np.mean([np.mean(figures[list(fold)]) for fold in folds]))


def field_report(
    problem: Problem, reference: Any, stage: FieldStage, depth: int | None
) -> FieldFit:
    """The result's :class:`~fpm.fitting.result.FieldFit`: the field and the side-by-side
    figures of the four parameters and the field, the validation cases (unseen until now)
    measured for both at ``depth`` (None: every layer)."""
    from .damping.validation import validate

    four = validate(
        problem, reference, model_stiffness(problem, stage.theta), depth, geometry=False
    )
    mine = validate(problem, reference, stage.field_stiffness(problem), depth, geometry=False)
    return FieldFit(
        returned=stage.returned,
        spring_factor=stage.spring_factor,
        kappa_factor=stage.kappa_factor,
        smoothness_weight=stage.weight,
        cv_weights=stage.weights,
        cv_error=stage.cv_error,
        cv_cases=stage.cv_cases,
        patterns=stage.patterns,
        four_parameter=ModelFigures(
            relative_discrepancy=stage.four_relative,
            validation_relative_discrepancy=four.relative,
            cv_error=stage.four_cv_error,
            cv_cases=stage.four_cv_cases,
        ),
        field=ModelFigures(
            relative_discrepancy=stage.field_relative,
            validation_relative_discrepancy=mine.relative,
            cv_error=stage.cv_error[stage.weights.index(stage.weight)],
            cv_cases=stage.cv_cases[stage.weights.index(stage.weight)],
        ),
        edges=stage.edges,
        iterations=stage.iterations,
        evaluations=stage.evaluations,
        seconds=stage.seconds,
    )


def field_parts(
    problem: Problem, reference: Any, damping: Any, theta: Sequence[float], depth: int | None
) -> tuple[FieldFit | None, Stiffness | list[float], list[str]]:
    """What the calibration's finalize needs of a field fit (``damping``: the damping stage,
    whose ``field`` holds it, or None): (the result's FieldFit or None, the returned model's
    stiffness (theta itself without a field), warnings)."""
    saved = getattr(damping, "field", None)
    if saved is None:
        return None, [float(t) for t in theta], []
    stage = FieldStage.from_dict(saved)
    notes = [stage.warning] if stage.warning else []
    return field_report(problem, reference, stage, depth), stage.stiffness(problem), notes
