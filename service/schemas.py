"""Response schemas (requests are :class:`fpm.spec.ProblemSpec`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from worker.status import CalibrationStatus, FemStatus, Phase


class ChainProgress(BaseModel):
    """Latest report of one annealing chain."""

    chain: int
    move: int = 0
    moves: int = 0
    temperature: float | None = None
    best_cost: float | None = Field(None, description="normalised cost (Eq. 2 / reference cost)")


class DampingProgress(BaseModel):
    """Latest report of the damping stage (two-stage method, stage 2)."""

    step: Literal["polish", "depth", "damping"] | None = Field(
        None,
        description="'polish' (local search of the stiffness from the best chain's), 'depth' "
        "(depth 'auto' on static equilibria), 'damping' (the fastest-settling d)",
    )
    runs: int = Field(0, description="d values tried (each a dynamic run of every load case)")
    d: float | None = Field(None, description="the last d tried, N s/m")
    total_steps: int | None = Field(
        None, description="its settle steps over all load cases (null: some did not settle)"
    )
    best_d: float | None = Field(None, description="the fastest-settling d so far, N s/m")
    best_total_steps: int | None = Field(None, description="its settle steps, all load cases")


class Progress(BaseModel):
    """Where a calibration is: its phase and stage, and the annealing's and the damping
    stage's latest reports."""

    phase: Phase = Field(
        description="queued, fem (the FEM reference), annealing (the chains: stage 1, the "
        "stiffness search, for two-stage), damping (two-stage stage 2: polish, depth, d), "
        "finalize, done"
    )
    method: Literal["two-stage", "paper"] = Field(description="the spec's annealing.method")
    stage: str = Field(description="what runs now, in words")
    stages: list[Phase] = Field(description="the phases this calibration goes through, in order")
    iterations: int = Field(0, description="annealing moves done, all chains together")
    total_iterations: int = Field(0, description="annealing moves in all, all chains together")
    temperature: float | None = Field(None, description="highest current chain temperature")
    best_cost: float | None = Field(None, description="best normalised cost over all chains")
    chains: list[ChainProgress] = []
    damping: DampingProgress | None = Field(
        None, description="the damping stage's report, once it has started (two-stage)"
    )


class ChainSummary(BaseModel):
    """One annealing chain's outcome."""

    chain: int
    x: list[float] = Field(description="best state: stiffness parameters, N/m (paper: then d)")
    cost: float = Field(description="its normalised cost")
    evaluations: int


class CalibrationResult(BaseModel):
    """The fitted parameters and how well they fit (keys of fpm's CalibrationResult)."""

    model_config = ConfigDict(extra="allow")

    method: str = Field(description="'two-stage' or 'paper'")
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
    k: float = Field(description="stiffness of the axis family (the one k for 'single'), N/m")
    stiffness: dict[str, float] = Field(description="k per spring family present, N/m")
    d: float = Field(description="nodal damping, N s/m: the fastest-settling at the spec's dt")
    d_min: float | None = Field(description="smallest d that still settles (two-stage), N s/m")
    depth: int = Field(description="penetration depth, layers")
    full_depth: int = Field(description="the deepest perturbed list, layers")
    cost: float = Field(description="Eq. (2) of the last dynamic run, m")
    static_cost: float = Field(description="Eq. (2) of the static equilibria, m")
    settle_steps: list[int] = Field(description="time steps to settle, per load case")
    settled: bool
    evaluations: int = Field(description="cost evaluations of the stiffness search")
    damping_runs: int = Field(description="dynamic runs of the d search")
    seconds: dict[str, float] = Field(description="wall time per stage, s")
    h: float = Field(description="shortest spring rest length, m")
    node_mass: dict[str, float] = Field(description="lumped node masses: min, max, mean, total, kg")
    warnings: list[str] = []
    history: list[float] = Field([], description="normalised cost per move, winning chain")
    chains: list[ChainSummary] = []


class Timings(BaseModel):
    """Unix times (s) and durations (s) of a calibration."""

    created: float
    started: float | None = None
    finished: float | None = None
    queued_seconds: float | None = None
    running_seconds: float | None = None


class CalibrationSummary(BaseModel):
    """One line of the calibration listing."""

    id: str
    name: str
    status: CalibrationStatus
    created: float
    parameter_set_id: str | None = None


class Calibration(BaseModel):
    """A calibration: status, progress, and the result once succeeded."""

    id: str
    name: str
    status: CalibrationStatus
    progress: Progress
    timings: Timings
    fem_reference_id: str
    fem_cached: bool = Field(description="the FEM reference was already stored at submission")
    result: CalibrationResult | None = None
    parameter_set_id: str | None = None
    error: str | None = None
    spec_hash: str


class CalibrationPage(BaseModel):
    """A page of calibrations, newest first."""

    items: list[CalibrationSummary]
    total: int
    offset: int
    limit: int


class FemReference(BaseModel):
    """A FEM reference: status, and once computed the nodes and displacements."""

    id: str
    status: FemStatus
    n_nodes: int | None = None
    load_cases: list[str] | None = None
    error: str | None = None
    nodes: list[list[float]] | None = Field(None, description="(N, 3) rest positions, m")
    displacements: list[list[list[float]]] | None = Field(
        None, description="(L, N, 3) nodal displacements per load case, m"
    )


class GeometrySummary(BaseModel):
    """The solid a parameter set was fitted on."""

    model_config = ConfigDict(extra="allow")

    type: str = Field(description="box, voxels or mesh")
    connectivity: str | None = Field(description="axis, axis+face or full")
    size: list[float] | None = Field(None, description="box size, m (boxes only)")
    nodes: int = Field(description="node count")
    h: float = Field(description="shortest spring rest length, m")


class Provenance(BaseModel):
    """Where a parameter set comes from."""

    model_config = ConfigDict(extra="allow")

    calibration_id: str
    spec_hash: str
    fem_hash: str
    method: str = Field(description="'two-stage' or 'paper'")
    seed: int
    chains: int
    evaluations: int


class ParameterSet(BaseModel):
    """A stored (stiffness, d, depth) with its material, geometry summary, fit and provenance."""

    model_config = ConfigDict(extra="allow")

    id: str
    name: str
    created: float
    k: float = Field(description="stiffness of the axis family (the one k for 'single'), N/m")
    stiffness: dict[str, float] = Field(description="k per spring family present, N/m")
    stiffness_mode: Literal["single", "families"] = Field(description="the spec's fpm.stiffness")
    stiffness_scale: list[float] = Field(description="per-axis stiffness factors (sx, sy, sz)")
    d: float = Field(description="nodal damping, N s/m (meaningful only with dt)")
    d_min: float | None = Field(description="smallest d that still settles (two-stage), N s/m")
    depth: int
    dt: float = Field(description="the time step the set was fitted at, s")
    material: dict[str, float]
    geometry: GeometrySummary
    relative_discrepancy: list[float] = Field(
        description="per load case, % (scale-free; the headline figure)"
    )
    loaded_discrepancy: list[float] = Field(description="per load case, loaded nodes only, %")
    discrepancy_h: list[float] = Field(
        description="per load case, % of h (the paper's unit; read it beside the relative figure)"
    )
    cost: float = Field(description="Eq. (2) of the last dynamic run, m")
    node_mass: dict[str, float] = Field(description="lumped node masses: min, max, mean, total, kg")
    warnings: list[str] = []
    provenance: Provenance


class ParameterSetPage(BaseModel):
    items: list[ParameterSet]
    total: int


class Health(BaseModel):
    """Liveness of the parts: Redis, the workers, the queue."""

    status: str = Field(description="'ok', or 'degraded' when no worker is alive")
    redis: bool
    workers: int = Field(
        description="alive workers: a heartbeat within the last heartbeat_window seconds"
    )
    silent_workers: int = Field(
        description="registered workers with no heartbeat for longer: dead (killed, lost) or hung"
    )
    heartbeat_window: int = Field(
        description="seconds without a heartbeat after which a worker counts as dead"
    )
    queued_jobs: int = Field(description="jobs waiting for a worker (both queues)")
    running_jobs: int = Field(description="jobs a worker is running")
    failed_jobs: int = Field(
        description="jobs that failed, kept for 7 days (jobs stopped by a cancel are not failures)"
    )
