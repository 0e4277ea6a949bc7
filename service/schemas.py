"""Response schemas (requests are :class:`fpm.spec.ProblemSpec`)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from worker.status import CalibrationStatus, FemStatus, Phase


class ChainProgress(BaseModel):
    """Latest report of one annealing chain."""

    chain: int
    move: int = 0
    moves: int = 0
    temperature: float | None = None
    best_cost: float | None = Field(None, description="normalised cost (Eq. 2 / reference cost)")


class Progress(BaseModel):
    """Where a calibration is: phase, moves done over all chains, temperature, best cost."""

    phase: Phase
    iterations: int = Field(0, description="annealing moves done, all chains together")
    total_iterations: int = Field(0, description="annealing moves in all, all chains together")
    temperature: float | None = Field(None, description="highest current chain temperature")
    best_cost: float | None = Field(None, description="best normalised cost over all chains")
    chains: list[ChainProgress] = []


class CalibrationResult(BaseModel):
    """The fitted parameters and how well they fit (keys of fpm's CalibrationResult)."""

    model_config = ConfigDict(extra="allow")

    k: float = Field(description="spring stiffness, N/m")
    d: float = Field(description="nodal damping, N s/m")
    depth: int = Field(description="penetration depth, layers")
    cost: float = Field(description="Eq. (2) at (k, d, depth), m")
    discrepancy: list[float] = Field(description="mean nodal discrepancy per load case, % of h")
    settle_steps: list[int] = Field(description="time steps to settle, per load case")
    settled: bool
    evaluations: int
    seconds: float = Field(description="wall time of the annealing, s")


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


class ParameterSet(BaseModel):
    """A stored (k, d, depth) with its material, geometry summary, fit and provenance."""

    model_config = ConfigDict(extra="allow")

    id: str
    name: str
    created: float
    k: float
    d: float
    depth: int
    dt: float = Field(description="the time step the set was fitted at, s")
    material: dict[str, float]
    geometry: dict[str, Any]
    discrepancy: list[float]
    provenance: dict[str, Any]


class ParameterSetPage(BaseModel):
    items: list[ParameterSet]
    total: int


class Health(BaseModel):
    """Liveness of the parts: Redis, the workers, the queue."""

    status: str = Field(description="'ok', or 'degraded' when no worker is alive")
    redis: bool
    workers: int
    queued_jobs: int
    running_jobs: int
    failed_jobs: int
