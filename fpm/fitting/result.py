"""What a calibration hands back: the fitted parameter set and how well it fits.

The one definition of the result: :func:`fpm.calibrate` returns a :class:`CalibrationResult`,
its fields in groups (``parameters``, ``fit``, ``settle``, ``reference``, ``run``); the worker
stores its :meth:`CalibrationResult.to_dict` as JSON, flat (one key per field, in the order of
:data:`STORED_FORM`, which names each key's group and field), and the REST answer
(``service.schemas``) derives from :data:`StoredResult`, the model of that flat form built
from the groups' fields, adding only the REST names. It needs pydantic and nothing numerical,
so the service can import it without loading the kernels.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field, create_model


class ChainSummary(BaseModel):
    """One annealing chain's outcome."""

    chain: int
    x: list[float] = Field(description="best state: stiffness parameters, N/m (paper: then d)")
    cost: float = Field(
        description="its normalised cost (families+volume: of the reduced linear model the "
        "chain anneals; the damping stage's polish then fits the static equilibria)"
    )
    evaluations: int


class ModelFigures(BaseModel):
    """One model's figures in a field fit's side-by-side comparison (static equilibria)."""

    relative_discrepancy: list[float] = Field(
        description="per load case, the relative discrepancy of its static equilibrium, %"
    )
    validation_relative_discrepancy: list[float] = Field(
        [], description="per validation case (never fitted), %"
    )
    cv_error: float = Field(
        description="cross-validation: the mean relative discrepancy, %, of the load cases "
        "left out (a force pattern at a time), each refitted without them; the mean over the "
        "patterns, each the mean of its cases"
    )
    cv_cases: list[float] = Field(description="per load case, its figure when left out, %")


class FieldFit(BaseModel):
    """fpm.stiffness 'field': the per-cell stiffness field, its smoothness weight and how it
    compares with the four-parameter (families+volume) fit (fpm.fitting.field)."""

    returned: bool = Field(
        description="the field is the returned model; false: it cross-validated no better "
        "than the four parameters (or could not be cross-validated), which are returned"
    )
    spring_factor: list[float] = Field(
        description="per hexahedron: the factor on the share of its family's k each cell gives "
        "its springs"
    )
    kappa_factor: list[float] = Field(description="per hexahedron: the factor on kappa")
    smoothness_weight: float = Field(description="the weight chosen by cross-validation")
    cv_weights: list[float] = Field(description="the smoothness weights tried, strongest first")
    cv_error: list[float] = Field(
        description="per weight tried, the field's mean left-out relative discrepancy, % "
        "(over the patterns, each the mean of its cases)"
    )
    cv_cases: list[list[float]] = Field(description="per weight, per load case left out, %")
    patterns: list[list[int]] = Field(
        description="the load cases grouped by force pattern (scaled copies together): the "
        "cross-validation's folds"
    )
    four_parameter: ModelFigures = Field(description="the families+volume fit's figures")
    field: ModelFigures = Field(description="the field's figures")
    edges: int = Field(description="neighbouring cell pairs the smoothness penalty runs over")
    iterations: int = Field(description="L-BFGS-B iterations of the final field fit")
    evaluations: int = Field(description="adjoint evaluations, cross-validation included")
    seconds: float = Field(description="wall time of the field fit, s")


class JobSpan(BaseModel):
    """One job of a calibration run by the service's workers (or one segment of the damping
    job, which hands its load cases out: store.timeline)."""

    name: str = Field(
        description="what it ran: 'FEM reference', 'chain 0', 'damping', 'damping: d <d>, load "
        "case <j>', 'damping (gather)', 'finalize'"
    )
    worker: str = Field(description="the worker that ran it")
    start: float = Field(description="Unix time it started, s")
    end: float = Field(description="Unix time it ended, s")
    cpu: float = Field(description="CPU seconds it used, all its threads, s")
    after: list[str] = Field([], description="the jobs it waited for (names)")
    task: str | None = Field(
        None,
        description="a damping-stage task's digest (worker.tasks.task_digest): two spans "
        "with one digest are one task run twice; None for the other jobs",
    )


class BoundHit(BaseModel):
    """A fitted parameter at or near one end of its search range (fpm.fitting.bounds)."""

    parameter: str = Field(description="its name: a spring family ('axis', ...), 'k' or 'kappa'")
    value: float = Field(description="the fitted value: N/m for a spring family, Pa for kappa")
    side: str = Field(description="'lower' or 'upper': the end it is at")
    bound: float = Field(description="that end of its range, in the value's unit")
    setting: str = Field(
        description="what sets that end: 'annealing.bounds.k', or 'derived' (from the material "
        "and h, not a spec setting: fpm.fitting.bounds)"
    )


class Floor(BaseModel):
    """What the model family reaches on a lattice like this one, as the manual documents it."""

    figure: float = Field(description="the documented worst relative discrepancy, %")
    what: str = Field(description="what was measured, on what")
    source: str = Field(description="the manual's page that records it")


class Cause(BaseModel):
    """A likely cause of a fit short of good, and the action that helps."""

    cause: str = Field(
        description="'large deformation', 'reference', 'lattice too coarse', 'nu near 0.5', "
        "'compliance', 'bound', 'model family' or 'unsettled'"
    )
    detail: str = Field(description="what was found, with the case or part and the figure")
    action: str = Field(description="what to change")


class Verdict(BaseModel):
    """How good the fit is, in one word and its reasons (thresholds: fpm.fitting.verdict)."""

    grade: str = Field(
        description="'good', 'fair' or 'poor' (a poor fit still succeeds: read its causes)"
    )
    basis: str = Field(
        description="'unseen': judged on the validation cases (never fitted); 'fitted': on the "
        "fitted load cases, there being none (they flatter the fit)"
    )
    worst: float = Field(description="the worst relative discrepancy on that basis, %")
    worst_case: str = Field(description="the case it is on")
    floor: Floor = Field(description="what the model family reaches on such a lattice")
    bounds: list[BoundHit] = Field(
        [], description="the fitted parameters at or near a bound of their search range"
    )
    causes: list[Cause] = Field([], description="likely causes when not good, with actions")
    summary: str = Field(description="the verdict in one line, for a table or a page")


class StepBudget(BaseModel):
    """``fpm.step_budget_us``: the depth a frame budget allows (:mod:`fpm.fitting.step_budget`)."""

    budget_us: float = Field(description="the budget asked for one step, microseconds")
    depth: int = Field(description="the deepest depth whose region step meets it, layers")
    met: bool = Field(description="whether it is met (False: even one layer is over it)")
    microseconds: list[float] = Field(
        description="per load case (fitted, then validation), a region step at that depth, µs"
    )
    nodes: int = Field(description="the largest region's nodes at that depth")
    probed: dict[str, float] = Field(description="depth probed -> the slowest case's µs")
    backend: str = Field(description="the runtime's backend that was timed (native, numba, numpy)")
    machine: str = Field(description="the machine timed: processor and cores")


class ModelParameters(BaseModel):
    """The fitted model: what an engine needs to run it (stiffness, damping, depth, the
    lattice's h and node masses, the per-cell field)."""

    stiffness_mode: str = Field(
        "single",
        description="the model fitted (fpm.stiffness): 'families+volume' (spring families "
        "assembled from cells plus a volume term), 'single' (the paper's model: one k), or "
        "'families'",
    )
    loads: str = Field(
        "node",
        description="how the lattice took a nodal force (fpm.loads, 'auto' resolved): 'node' "
        "(all of it at its node) or 'hat' (shared over the nodes around it as the refined "
        "reference spreads it); an engine applies forces the same way (the export's load_shares)",
    )
    k: float = Field(description="stiffness of the axis family (the one k for 'single'), N/m")
    stiffness: dict[str, float] = Field(
        description="k per spring family present, N/m (all equal for 'single'); with "
        "'families+volume' a spring gets its family's k times its cells' shares (an interior "
        "spring k, a surface one less). With material.regions also each other region's "
        "families and kappa by name ('axis[name]', ..., 'kappa[name]', Pa); with a "
        "transversely isotropic material its fitted 'axial_scale'"
    )
    volume_stiffness: float | None = Field(
        None,
        description="kappa, Pa: the volume stiffness of every cell ('families+volume'; None "
        "for the spring-only models); with material.regions the base region's",
    )
    regions: list[dict[str, Any]] | None = Field(
        None,
        description="material.regions: per region present, base (the cells of no region) "
        "first: name, cells, youngs_modulus (Pa), poisson_ratio, density (kg/m^3), the fitted "
        "stiffness ({family: k}, N/m) and volume_stiffness (kappa, Pa); absent without regions",
        exclude_if=lambda v: v is None,
    )
    d: float = Field(description="nodal damping, N s/m: the fastest-settling at the spec's dt")
    depth: int = Field(description="penetration depth, layers")
    full_depth: int = Field(description="the deepest perturbed list, layers")
    step_budget: StepBudget | None = Field(
        None,
        description="fpm.step_budget_us: the depth it allows and what was measured; absent "
        "without a budget",
        exclude_if=lambda v: v is None,
    )
    h: float = Field(description="shortest spring rest length, m")
    node_mass: dict[str, float] = Field(description="lumped node masses: min, max, mean, total, kg")
    field: FieldFit | None = Field(
        None,
        description="fpm.stiffness 'field': the per-cell field and the side-by-side figures; "
        "absent for the other modes",
        exclude_if=lambda v: v is None,
    )


class FitFigures(BaseModel):
    """How well the model fits: the costs, the discrepancies per load case and per validation
    case, the load compliance ratios and the verdict."""

    cost: float = Field(description="Eq. (2) of the last dynamic run at (stiffness, d, depth), m")
    static_cost: float = Field(description="Eq. (2) of the static equilibria, m")
    relative_discrepancy: list[float] = Field(
        description="per load case: 100 sum_i |p_i - q_i| / sum_i |q_i|, % (scale-free; the "
        "headline figure of the fit)"
    )
    loaded_discrepancy: list[float] = Field(
        description="the same at the loaded nodes only, relative to their FEM displacement, %"
    )
    discrepancy_h: list[float] = Field(
        description="mean nodal discrepancy per load case, % of h (the paper's unit; shrinks "
        "with soft materials and small loads, so read it beside the relative figure)"
    )
    validation_cases: list[str] = Field(
        [], description="names of the validation cases (never in the cost), in spec order"
    )
    validation_relative_discrepancy: list[float] = Field(
        [],
        description="per validation case, the relative discrepancy at the fitted parameters, "
        "% (the honest figure: loads the fit never saw)",
    )
    validation_discrepancy_h: list[float] = Field(
        [], description="per validation case, mean nodal discrepancy, % of h"
    )
    compliance_ratio: list[float | None] = Field(
        [],
        description="per load case, the load compliance ratio: sum_i f_i . u_i over its "
        "loaded nodes, the model's over the reference's (1.0: a probe there feels the "
        "reference's stiffness; 1.5: 1.5 times too soft; 0.8: 1.25 times too stiff); null "
        "where the load does no work on the reference; empty in results stored before it",
    )
    validation_compliance_ratio: list[float | None] = Field(
        [], description="the same per validation case"
    )
    verdict: Verdict | None = Field(
        None,
        description="how good the fit is ('good', 'fair', 'poor'), on what basis, beside what "
        "the model family reaches, the parameters at a bound and the likely causes; null in "
        "results stored before it",
    )

    @property
    def mean_relative_discrepancy(self) -> float:
        """Mean over the load cases, %."""
        return sum(self.relative_discrepancy) / len(self.relative_discrepancy)


class SettleFigures(BaseModel):
    """How the model's runs settle: the time step and step cap, the steps per load case, the
    damping search's bounds and prediction, the settle criterion and the distances reached
    (stored as ``dt``, ``max_steps``, ``settle_steps``, ``settled``, ``d_min``, ``d_predicted``,
    ``settle_stiffness`` and ``settle_distance*``)."""

    dt: float | None = Field(
        None, description="the time step d was fitted at and settle_steps count, s"
    )
    max_steps: int | None = Field(
        None,
        description="the cap on each run's steps: the spec's fpm.max_steps, or its 'auto' "
        "resolved (three times the predicted steps of the slowest load case); null in results "
        "stored before the field existed",
    )
    steps: list[int] = Field(description="time steps to settle, per load case")
    settled: bool = Field(description="every load case settled within max_steps")
    d_min: float | None = Field(
        description="smallest d that still settles every load case (two-stage), N s/m"
    )
    d_predicted: float | None = Field(
        None,
        description="the fastest-settling d predicted from the lattice's slowest modes before "
        "any run (two-stage; the search starts there and confirms it), N s/m; null: no "
        "prediction (the search started from critical-damping estimates, or the paper method)",
    )
    stiffness: list[float] | None = Field(
        None,
        description="per load case, the settle criterion of a run that has no equilibrium to "
        "read (an engine running the JSON export), N/m: settled once the 2-norm of its "
        "unbalanced nodal forces is below this times the 2-norm of its displacements "
        "(fpm.settle_distance, 0.01 for 'auto', times the stiffness of the lattice's softest "
        "mode: a bound on the distance); null on the force criterion (fpm.settle_tolerance "
        "named, the paper method)",
    )
    distance: list[float] | None = Field(
        None,
        description="per load case, the distance from its static equilibrium the fit's runs "
        "settled within, relative to its displacement (sums of nodal distances, as Eq. 2): "
        "fpm.settle_distance, or for 'auto' 1/20 of the case's static discrepancy, between "
        "1e-4 and 0.01; null on the force criterion",
    )
    distance_estimated: list[float] | None = Field(
        None,
        description="per load case, the settled state's distance from its static equilibrium "
        "as its run read it where it stopped (with what its velocities still carry along the "
        "softest mode), relative to the equilibrium's displacement; null on the force "
        "criterion",
    )
    distance_measured: list[float] | None = Field(
        None,
        description="per load case, the settled state's distance from its static equilibrium, "
        "measured against that equilibrium solved: the sum of the nodal differences over the "
        "sum of the equilibrium's nodal displacements; null on the force criterion",
    )


class ReferenceFacts(BaseModel):
    """What the fit was measured against (stored as ``reference``, ``reference_error``,
    ``validation_reference_error`` and ``reference_refinements``)."""

    label: str = Field(
        "fem",
        description="what the fit was measured against: 'fem-linear-selective', "
        "'fem-linear-full', 'fem-linear-tet10' (10-node tetrahedra on reference.mesh), "
        "'fem-neo-hookean-selective', 'fem-neo-hookean-full' or 'supplied' (the spec's "
        "reference.displacements); "
        "'fem' in results stored before the field existed",
    )
    error: list[float] | None = Field(
        None,
        description="per load case, the reference's estimated error, %: the relative change "
        "at the lattice nodes from its last refinement to the one before (reference.refine; "
        "for hexahedra as given, from one refinement with the forces spread); above 5% a "
        "warning says the reference does not resolve that load; null when not estimated",
    )
    validation_error: list[float] | None = Field(
        None, description="the same per validation case, %; null when not estimated"
    )
    refinements: int | None = Field(
        None,
        description="uniform refinements of the reference's mesh the fit was measured against "
        "(0: the mesh or hexahedra as given); null for a supplied reference",
    )


class RunFacts(BaseModel):
    """What the calibration took: its evaluations and runs, its time per stage, the chains
    and, calibrated by the service, its jobs and their critical path."""

    evaluations: int = Field(description="cost evaluations over all chains (and the polish)")
    damping_runs: int = Field(description="dynamic runs of the d search")
    seconds: dict[str, float] = Field(
        description="wall time per stage, s: stiffness (parallel chains count once: the "
        "slowest), damping, finalize"
    )
    history: list[float] = Field([], description="normalised cost per move, winning chain")
    chains: list[ChainSummary] = []
    jobs: list[JobSpan] | None = Field(
        None,
        description="calibrated by the service: every job (and the damping job's two "
        "segments around the load-case runs it handed out), in start order: worker, start, "
        "end, CPU seconds and the jobs it waited for; absent when calibrated in-process",
        exclude_if=lambda v: v is None,
    )
    critical_path: list[str] | None = Field(
        None,
        description="the longest chain of jobs each waiting for the one before (names, first "
        "first): what the calibration takes with a free worker for every job",
        exclude_if=lambda v: v is None,
    )
    critical_path_seconds: float | None = Field(
        None,
        description="the critical path's length, s (the sum of its jobs' durations: queueing "
        "left out)",
        exclude_if=lambda v: v is None,
    )


class CalibrationResult(BaseModel):
    """The fitted parameters and how well they fit, in groups (units in each field's
    description); :meth:`to_dict` is its stored form, flat (:data:`StoredResult`)."""

    method: str = Field(description="'two-stage' or 'paper'")
    parameters: ModelParameters = Field(description="the fitted model")
    fit: FitFigures = Field(description="how well it fits")
    settle: SettleFigures = Field(description="how its runs settle")
    reference: ReferenceFacts = Field(description="what it was measured against")
    run: RunFacts = Field(description="what the calibration took")
    warnings: list[str] = Field(
        [], description="what the user should know (outside small strain, static/dynamic mismatch)"
    )

    def to_dict(self) -> dict[str, Any]:
        """The stored form (JSON-able): flat, the keys of :data:`STORED_FORM` in its order,
        those a group leaves out (``regions``, ``field``, ``jobs`` ... when None) left out."""
        grouped = self.model_dump()
        stored = {}
        for key, (group, name) in STORED_FORM.items():
            part = grouped if group is None else grouped[group]
            if name in part:
                stored[key] = part[name]
        return stored


STORED_FORM: dict[str, tuple[str | None, str]] = {
    "method": (None, "method"),
    "stiffness_mode": ("parameters", "stiffness_mode"),
    "loads": ("parameters", "loads"),
    "reference": ("reference", "label"),
    "reference_error": ("reference", "error"),
    "validation_reference_error": ("reference", "validation_error"),
    "reference_refinements": ("reference", "refinements"),
    "k": ("parameters", "k"),
    "stiffness": ("parameters", "stiffness"),
    "volume_stiffness": ("parameters", "volume_stiffness"),
    "regions": ("parameters", "regions"),
    "dt": ("settle", "dt"),
    "d": ("parameters", "d"),
    "d_min": ("settle", "d_min"),
    "d_predicted": ("settle", "d_predicted"),
    "max_steps": ("settle", "max_steps"),
    "depth": ("parameters", "depth"),
    "full_depth": ("parameters", "full_depth"),
    "step_budget": ("parameters", "step_budget"),
    "cost": ("fit", "cost"),
    "static_cost": ("fit", "static_cost"),
    "relative_discrepancy": ("fit", "relative_discrepancy"),
    "loaded_discrepancy": ("fit", "loaded_discrepancy"),
    "discrepancy_h": ("fit", "discrepancy_h"),
    "validation_cases": ("fit", "validation_cases"),
    "validation_relative_discrepancy": ("fit", "validation_relative_discrepancy"),
    "validation_discrepancy_h": ("fit", "validation_discrepancy_h"),
    "compliance_ratio": ("fit", "compliance_ratio"),
    "validation_compliance_ratio": ("fit", "validation_compliance_ratio"),
    "verdict": ("fit", "verdict"),
    "settle_steps": ("settle", "steps"),
    "settled": ("settle", "settled"),
    "settle_stiffness": ("settle", "stiffness"),
    "settle_distance": ("settle", "distance"),
    "settle_distance_estimated": ("settle", "distance_estimated"),
    "settle_distance_measured": ("settle", "distance_measured"),
    "evaluations": ("run", "evaluations"),
    "damping_runs": ("run", "damping_runs"),
    "seconds": ("run", "seconds"),
    "history": ("run", "history"),
    "h": ("parameters", "h"),
    "node_mass": ("parameters", "node_mass"),
    "warnings": (None, "warnings"),
    "chains": ("run", "chains"),
    "jobs": ("run", "jobs"),
    "critical_path": ("run", "critical_path"),
    "critical_path_seconds": ("run", "critical_path_seconds"),
    "field": ("parameters", "field"),
}
"""The stored form's keys, in the order stored and answered: each the (group of
:class:`CalibrationResult`, field) it holds; None: a field of the result itself."""


def _stored_result() -> type[BaseModel]:
    """The model of the stored form: a field per key of :data:`STORED_FORM`, in its order,
    with its group field's type, default and description."""
    fields: dict[str, Any] = {}
    for key, (group, name) in STORED_FORM.items():
        owner: Any = (
            CalibrationResult.model_fields[group].annotation if group else CalibrationResult
        )
        info = owner.model_fields[name]
        fields[key] = (info.annotation, info)
    return create_model(
        "StoredResult",
        __doc__="A calibration result as stored and answered: the fields of "
        "CalibrationResult's groups, flat (its to_dict)",
        **fields,
    )


StoredResult = _stored_result()
"""The stored form of a :class:`CalibrationResult` (its :meth:`~CalibrationResult.to_dict`),
flat: the model the REST answer (``service.schemas.CalibrationResult``) derives from."""
