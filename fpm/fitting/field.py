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
(:func:`cell_adjacency`: cells sharing a face; edges between two regions can be dropped, so a
region's field is never smoothed into its neighbour's).

**The gradient, by the adjoint.** At an equilibrium, g(u, k) = dE/du = 0 over the list's free
nodes. For a cost J(u), dJ/dk = -lambda . dg/dk with H lambda = dJ/du, H = dg/du the exact
tangent (:meth:`fpm.dynamics.equilibrium.StaticSolver.linear_solve`): one linear solve per load
case, whatever the number of parameters. Per spring lambda . dg/dk_s = (|r_s| - L_s) n_s .
(lambda_j - lambda_i), per cell lambda . dg/dkappa_c = (V_c - V0_c) / V0_c sum_n g_n . lambda_n
(:meth:`fpm.dynamics.spring_system.SpringSystem.sensitivity`), then through the cells' shares
to the factors (:class:`FieldMap`). tests/test_field.py checks it against central differences.

**The smoothness weight, by cross-validation.** Leave one force pattern out at a time
(:func:`load_patterns`: load cases that are scaled copies of one another are one pattern, as
leaving out a scaled copy tests only the force's size): refit the four parameters on the
other cases (:class:`FamilyMap`, the same adjoint), fit the field on them for each weight of
:data:`WEIGHTS` (strongest first, each starting from the last), and measure the left-out
cases (relative discrepancy, %; the mean over the left-out patterns, each the mean of its
cases, :func:`_mean`); where the means at those weights differ by more than
:data:`CV_FLAT`, every fold also fits at the geometric mean of the best two (coarse to fine).
The weight with the smallest mean left-out figure is chosen and the field is fitted on every
load case at it. If even that mean is no better than the
four parameters' own left-out mean, or if every load case is one pattern (nothing to predict),
the field is not returned: the four-parameter fit is, with a warning saying why
(:class:`FieldStage`; the field's figures are still reported beside the four parameters').
The spec's validation cases take no part: they are measured at the end, for both
(:func:`field_report`). The folds run one after another; within an evaluation the load
cases run on threads, each with its own static solver (:class:`Solvers`).

**Material regions.** Each cell's factors multiply its own region's families and kappa, the
folds refit every region's parameters, and the smoothness graph has no edge between two
regions (:func:`fit_field`'s default).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import minimize

from ..dynamics.equilibrium import StaticSolver
from ..fem.linear_solver import NegativeCurvature, SingularStiffnessError
from ..model.forces import Stiffness
from ..model.hexahedron import NATURAL
from ..model.problem import Problem, load_patterns
from ..model.stiffness import (
    axis_factors,
    cell_shares,
    field_stiffness,
    field_terms,
    linear_parts,
    model_stiffness,
)
from .bounds import stiffness_bounds
from .result import FieldFit, ModelFigures

WEIGHTS = (1.0, 0.01)
"""Smoothness weights the cross-validation tries first, strongest first (units: the normalised
cost per mean squared log-factor step between neighbouring cells); where their left-out means
differ by more than :data:`CV_FLAT`, the geometric mean of the best and its neighbour is tried
too (coarse to fine). On the organ at 5 mm the mean left-out figure was 5.62 / 5.57 / 5.58 /
5.58% at 1 / 0.1 / 0.01 / 0.001 (bench field), at 3 mm 1.77 / 1.84 / 1.79% at 1 / 0.1 / 0.01:
flat, so two weights two decades apart."""
CV_FLAT = 0.1
"""Left-out means (%, absolute) closer than this are flat: no weight between them is tried.
Within one fold's fit the left-out figure moves by 0.1-0.7 points from one L-BFGS-B iteration
to the next (the organ at 5 mm), so finer differences are noise."""
SPAN = math.log(10.0)
"""Each log factor stays within +-this (a cell's springs or kappa at most 10x up or down)."""
CV_ITERATIONS = 10
"""L-BFGS-B iterations of a fold's field fit at one weight (it starts from the last weight's).
6 were tried on the organ at 3 mm: the fields at weight 1 stopped short (left out 1.91%
against 1.79% after 10), the coarse means then differed by more than :data:`CV_FLAT`, the
middle weight was fitted too, and the stage cost as much (111 evaluations against 114)."""
FINAL_ITERATIONS = 15
"""L-BFGS-B iterations of the field fit on every load case at the chosen weight. On the organ
at 5 mm the normalised cost went 0.0467 (first iteration), 0.0410 (10), 0.0406 (15), 0.0402
(30): past 15 the fit on the given loads improves by 1% of itself."""
FOUR_ITERATIONS = 5
"""L-BFGS-B iterations of a fold's refit of the four parameters (from the fit on every case)."""
ADJOINT_RTOL = 1e-2
"""Relative residual of the adjoint solves in a fit (multigrid CG; exact LU on small lists):
the gradient to about this, enough for L-BFGS-B. On the organ at 5 mm an adjoint took 8-9 CG
iterations at 1e-2, 12-13 at 1e-3, 14-16 at 1e-4, and 12 iterations of the field fit ended
at the same normalised cost (0.04076, 0.04078, 0.04076)."""
FIT_TOLERANCE = 1e-6
"""The static equilibria in a fit are solved to this (largest unbalanced nodal force over the
largest applied one; the reported figures to the solver's default, a tenth of the settle
tolerance)."""
FAILED = 1e3
"""The normalised cost reported where a load case has no equilibrium (L-BFGS-B backtracks)."""

Progress = Callable[[dict[str, Any]], None]


class FieldError(RuntimeError):
    """A load case without a static equilibrium where the field fit needs one."""


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


@dataclass
class CaseGradient:
    """One load case's Eq. (2) cost at an equilibrium and its adjoint gradient.

    Attributes:
        cost: sum_i |p_i - q_i| over every node, m.
        springs: (S,) dcost/dk_s, m / (N/m).
        kappa: (H,) dcost/dkappa_c, m / Pa (zeros without a volume term).
        displacements: (N, 3) the equilibrium, m.
        adjoint: (N, 3) lambda, the tangent's solution for dcost/du, m/N.
    """

    cost: float
    springs: np.ndarray
    kappa: np.ndarray
    displacements: np.ndarray
    adjoint: np.ndarray


def case_gradient(
    solver: StaticSolver,
    load_case: int,
    reference: np.ndarray,
    stiffness: Stiffness,
    depth: int | None,
    *,
    tolerance: float | None = None,
    rtol: float = ADJOINT_RTOL,
    guess: np.ndarray | None = None,
) -> CaseGradient:
    """The cost of ``load_case``'s static equilibrium at ``stiffness`` against ``reference``
    (N, 3), m, and its gradient by the stiffness of every spring and cell (this module's
    docstring: one adjoint solve with the exact tangent, CG starting from ``guess`` (N, 3),
    e.g. the last adjoint of the load case; the result's ``adjoint``).

    Raises:
        FieldError: the load case has no static equilibrium there.
    """
    problem = solver.problem
    eq = solver.solve(load_case, stiffness, depth, tolerance=tolerance)
    if not eq.converged:
        raise FieldError(f"load case {problem.load_cases[load_case].name!r}: {eq.message}")
    error = eq.displacements - reference
    size = np.sqrt(np.einsum("ij,ij->i", error, error))
    system, _ = solver.system(load_case, depth)
    pull = np.zeros_like(error)  # dcost/du on the free nodes (the others do not move)
    free = system.free[size[system.free] > 0]
    pull[free] = error[free] / size[free, None]
    u = eq.displacements[system.free]
    k = system.parameters(stiffness)
    tangent = system.tangent(u, k, modified=False)
    try:
        adjoint = solver.linear_solve(load_case, depth, tangent, pull, guess=guess, rtol=rtol)
    except (NegativeCurvature, SingularStiffnessError):  # rare: LU on the exact tangent
        adjoint = np.zeros_like(pull)
        rhs = np.ascontiguousarray(pull[system.free]).ravel()
        adjoint[system.free] = sp.linalg.spsolve(tangent.tocsc(), rhs).reshape(-1, 3)
    spring_part, cell_part = system.sensitivity(u, adjoint[system.free])
    springs = np.zeros(len(stiffness.springs))
    springs[system.springs] = -spring_part
    kappa = np.zeros(0 if stiffness.volume is None else len(stiffness.volume))
    if len(kappa):
        kappa[system.cell_ids] = -cell_part
    return CaseGradient(float(size.sum()), springs, kappa, eq.displacements, adjoint)


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


class Solvers:
    """A static solver per load case (``solvers[j]`` serves load case j; one solver may serve
    several, serially) and the threads an evaluation's load cases run on. Each solver keeps
    its load case's warm starts and multigrid hierarchy, so an answer does not depend on the
    number of threads (:class:`~fpm.dynamics.equilibrium.StaticSolver` is not thread-safe:
    give distinct solvers when ``threads`` > 1)."""

    def __init__(self, solvers: Sequence[StaticSolver], threads: int = 1):
        self.solvers = list(solvers)
        if threads > 1 and len({id(s) for s in self.solvers}) < len(self.solvers):
            raise ValueError("load cases on threads need a solver each")
        self.pool = ThreadPoolExecutor(threads) if threads > 1 else None

    def __getitem__(self, load_case: int) -> StaticSolver:
        return self.solvers[load_case]

    def map(self, work: Callable[[int], Any], cases: Sequence[int]) -> list[Any]:
        """``[work(j) for j in cases]``, on the threads."""
        if self.pool is None:
            return [work(j) for j in cases]
        return list(self.pool.map(work, cases))

    def relative(
        self, reference: np.ndarray, cases: Sequence[int], stiffness: Stiffness, depth: int | None
    ) -> list[float]:
        """:func:`relative` of each of ``cases``, each by its own solver."""
        return self.map(lambda j: relative(self[j], reference, [j], stiffness, depth)[0], cases)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()


class Objective:
    """f(x) = Eq. (2) over ``cases`` / their reference cost + weight * smoothness, and its
    gradient (L-BFGS-B's fun with jac=True; the load cases on ``solvers``' threads, summed in
    case order); counts evaluations."""

    def __init__(
        self,
        solvers: Solvers,
        reference: np.ndarray,
        cases: Sequence[int],
        depth: int | None,
        parameters: Parameters,
        weight: float = 0.0,
        tolerance: float | None = FIT_TOLERANCE,
    ):
        self.solvers, self.reference, self.cases = solvers, reference, list(cases)
        self.depth, self.parameters, self.weight = depth, parameters, weight
        self.tolerance = tolerance
        self.scale = float(sum(np.linalg.norm(reference[j], axis=1).sum() for j in self.cases))
        self.evaluations = 0
        self.adjoints: dict[int, np.ndarray] = {}  # the last adjoint per load case: CG's start

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.evaluations += 1
        stiffness = self.parameters.stiffness(x)
        smooth, smooth_grad = self.parameters.smoothness(x)

        def one(j: int) -> CaseGradient:
            return case_gradient(
                self.solvers[j], j, self.reference[j], stiffness, self.depth,
                tolerance=self.tolerance, guess=self.adjoints.get(j),
            )  # fmt: skip

        try:
            found = self.solvers.map(one, self.cases)
        except FieldError:
            return FAILED, self.weight * smooth_grad
        total = 0.0
        springs = np.zeros(len(stiffness.springs))
        kappa = np.zeros(0 if stiffness.volume is None else len(stiffness.volume))
        for j, g in zip(self.cases, found, strict=True):
            self.adjoints[j] = g.adjoint
            total += g.cost
            springs += g.springs
            kappa += g.kappa
        grad = self.parameters.pull_back(x, springs, kappa) / self.scale
        return total / self.scale + self.weight * smooth, grad + self.weight * smooth_grad


def minimise(objective: Objective, x: np.ndarray, iterations: int) -> tuple[np.ndarray, int]:
    """L-BFGS-B from x within the parameters' bounds; returns (x, iterations taken)."""
    r = minimize(
        objective,
        x,
        jac=True,
        method="L-BFGS-B",
        bounds=objective.parameters.bounds(),
        options={"maxiter": iterations, "maxfun": 2 * iterations, "ftol": 1e-9, "gtol": 1e-9},
    )
    return np.asarray(r.x), int(r.nit)


def relative(
    solver: StaticSolver, reference: np.ndarray, cases: Sequence[int], stiffness: Stiffness,
    depth: int | None,
) -> list[float]:  # fmt: skip
    """The relative discrepancy, %, of each of ``cases`` at its static equilibrium (nan where
    there is none)."""
    out = []
    for j in cases:
        eq = solver.solve(j, stiffness, depth)
        q = reference[j]
        if not eq.converged:
            out.append(float("nan"))
            continue
        error = np.linalg.norm(eq.displacements - q, axis=1).sum()
        out.append(float(100 * error / np.linalg.norm(q, axis=1).sum()))
    return out


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
    edges: np.ndarray | None = None,
    iterations: tuple[int, int, int] = (FOUR_ITERATIONS, CV_ITERATIONS, FINAL_ITERATIONS),
    threads: int | None = None,
    progress: Progress | None = None,
) -> FieldStage:
    """The field on top of the families+volume fit ``theta``, its smoothness weight chosen by
    cross-validation (this module's docstring), at ``depth``.

    The folds leave out one force pattern at a time (:func:`load_patterns`: scaled copies of
    one load are one pattern). With a single pattern there is no other load to predict: the
    folds then leave out one load case at a time to choose the weight, the field is fitted
    and reported, but the four parameters are returned (a warning says why).

    Each fold fits at ``weights`` (strongest first, each from the last); where the best two
    of their left-out means differ by more than :data:`CV_FLAT`, every fold also fits at the
    geometric mean of the two, from the stronger one's field (coarse to fine).

    Args:
        reference: (L, N, 3) the load cases' reference displacements, m (the validation cases
            are not given: they stay unseen).
        solver: the static solver of the first load case (its hierarchies and warm starts are
            reused); the others get their own.
        edges: the smoothness graph (default: :func:`cell_adjacency` of the hexahedra, cut
            between material regions).
        iterations: L-BFGS-B iterations of a fold's four-parameter refit, of a fold's field
            fit at one weight, and of the final field fit.
        threads: load cases solved at once in an evaluation (None: one per core; each load
            case has its own static solver, so the answer does not depend on it).
    """
    four_iterations, cv_iterations, final_iterations = iterations
    t0 = time.perf_counter()
    cases = list(range(len(problem.load_cases)))
    if len(cases) < 2:
        raise ValueError("a stiffness field needs two load cases or more to cross-validate")
    hexahedra = problem.solid.elements()
    if hexahedra is None:
        raise ValueError("a network geometry has no cells for a stiffness field")
    if edges is None:
        labels = None if problem.regions is None else problem.regions.cells
        edges = cell_adjacency(hexahedra, labels)
    theta = [float(t) for t in theta]
    patterns = load_patterns(problem)
    folds = patterns if len(patterns) > 1 else [[j] for j in cases]
    family = FamilyMap(problem)
    workers = max(1, min(len(cases), threads or os.cpu_count() or 1))
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
    pattern given at three sizes counts once, as one given at one size does: a mean over the
    cases would weigh it three times in telling whether the field predicts other loads (the
    paper's cube with a second pattern: the field left out 3.7% on the pulls and 3.0% on the
    push, the four parameters 3.3-3.4% and 4.0%; per case 3.55 against 3.50%, per pattern 3.35
    against 3.67%)."""
    if not np.isfinite(figures).all():
        return float("inf")
    return float(np.mean([np.mean(figures[list(fold)]) for fold in folds]))


def field_report(
    problem: Problem, reference: Any, stage: FieldStage, depth: int | None
) -> FieldFit:
    """The result's :class:`~fpm.fitting.result.FieldFit`: the field and the side-by-side
    figures of the four parameters and the field, the validation cases (unseen until now)
    measured for both at ``depth`` (None: every layer)."""
    from .validation import validate

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
