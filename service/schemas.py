"""Response schemas (requests are :class:`fpm.model.spec.ProblemSpec`)."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field, model_validator
from pydantic.json_schema import SkipJsonSchema

from fpm.fitting.result import StoredResult
from store.records import ParameterSetRecord
from store.status import CalibrationStatus, FemStatus, Phase


def utc(t: float) -> datetime:
    """A Unix time (s) as an aware UTC datetime (answered as ISO 8601, e.g.
    ``2026-01-02T03:04:05.678000Z``)."""
    return datetime.fromtimestamp(t, timezone.utc)


def _old_name(data: Any, new: str, old: str) -> Any:
    """Fill the field ``new`` from ``old`` (and back), for records and callers that know only
    one of the two names."""
    if isinstance(data, dict) and (new in data) != (old in data):
        data = dict(data)
        if new in data:
            data[old] = data[new]
        else:
            data[new] = data[old]
    return data


OLD_D = (
    "the same value under its old name; kept for existing clients and left out of this "
    "document, since a property named 'd' breaks generated clients"
)


class ChainProgress(BaseModel):
    """Latest report of one annealing chain."""

    chain: int
    move: int = 0
    moves: int = 0
    temperature: float | None = None
    best_cost: float | None = Field(None, description="normalised cost (Eq. 2 / reference cost)")


class DampingProgress(BaseModel):
    """Latest report of the damping stage (two-stage method, stage 2)."""

    step: Literal["polish", "depth", "field", "damping"] | None = Field(
        None,
        description="'polish' (local search of the stiffness from the best chain's), 'depth' "
        "(depth 'auto' on static equilibria), 'field' (fpm.stiffness 'field': the per-cell "
        "factors and their smoothness, by cross-validation), 'damping' (the fastest-settling d)",
    )
    runs: int = Field(0, description="d values tried (each a dynamic run of every load case)")
    last_d: float | None = Field(None, description="the last d tried, N s/m")
    d: SkipJsonSchema[float | None] = Field(None, description=f"last_d: {OLD_D}")
    total_steps: int | None = Field(
        None, description="its settle steps over all load cases (null: some did not settle)"
    )
    best_d: float | None = Field(None, description="the fastest-settling d so far, N s/m")
    best_total_steps: int | None = Field(None, description="its settle steps, all load cases")

    @model_validator(mode="before")
    @classmethod
    def _names(cls, data: Any) -> Any:
        return _old_name(data, "last_d", "d")


class FemProgress(BaseModel):
    """The FEM reference's refinement while it runs (``reference.refine`` a number or "auto";
    empty before its first level and for a reference solved in one piece)."""

    level: int | None = Field(
        None, description="the level being solved: uniform refinements of the mesh as given"
    )
    fem_nodes: int | None = Field(None, description="the FEM's nodes at that level")
    last_change: float | None = Field(
        None,
        description="the largest change, %, between the last two levels solved (null before "
        "two): 'auto' stops below 1% or at reference.node_budget",
    )


class Progress(BaseModel):
    """Where a calibration is: its phase and stage, and the annealing's and the damping
    stage's latest reports."""

    phase: Phase = Field(
        description="queued, fem (the FEM reference), annealing (the chains: stage 1, the "
        "stiffness search, for two-stage), damping (two-stage stage 2: polish, depth, d), "
        "finalize, done"
    )
    method: Literal["two-stage", "paper"] = Field(description="the spec's annealing.method")
    stage: str = Field(
        description="what runs now, in words, after its number ('stage 2 of 4: stiffness "
        "search ...')"
    )
    stages: list[Phase] = Field(
        description="the stages of a calibration of this method, in order: fem (done at once "
        "when a stored reference is reused, see fem_cached), annealing, damping (two-stage), "
        "finalize"
    )
    stage_number: int | None = Field(
        None, description="the stage running, 1-based in stages (null while queued and when done)"
    )
    iterations: int = Field(0, description="annealing moves done, all chains together")
    total_iterations: int = Field(0, description="annealing moves in all, all chains together")
    temperature: float | None = Field(None, description="highest current chain temperature")
    best_cost: float | None = Field(None, description="best normalised cost over all chains")
    chains: list[ChainProgress] = []
    damping: DampingProgress | None = Field(
        None, description="the damping stage's report, once it has started (two-stage)"
    )
    fem: FemProgress | None = Field(
        None, description="the FEM reference's refinement level, while it runs (phase fem)"
    )


class CalibrationResult(StoredResult):  # type: ignore[misc, valid-type]
    """The fitted parameters and how well they fit.

    :class:`fpm.fitting.result.CalibrationResult` (the stored result is its ``to_dict``), with
    ``damping`` beside ``d`` (the name generated clients can use) and any field a record of an
    older version holds.
    """

    model_config = ConfigDict(extra="allow")

    d: SkipJsonSchema[float] = Field(description=f"damping: {OLD_D}")
    damping: float = Field(
        description="nodal damping d, N s/m: the fastest-settling at the spec's dt"
    )

    @model_validator(mode="before")
    @classmethod
    def _names(cls, data: Any) -> Any:
        return _old_name(data, "damping", "d")


class Timings(BaseModel):
    """When a calibration was created, started and finished (ISO 8601 UTC, and as Unix times
    in s), and how long it queued and ran (s)."""

    created: float = Field(description="Unix time, s (created_at: the same in ISO 8601)")
    started: float | None = Field(None, description="Unix time, s")
    finished: float | None = Field(None, description="Unix time, s")
    queued_seconds: float | None = None
    running_seconds: float | None = None

    @computed_field  # type: ignore[prop-decorator]
    @property
    def created_at(self) -> datetime:
        """Submitted, ISO 8601 UTC."""
        return utc(self.created)

    @computed_field  # type: ignore[prop-decorator]
    @property
    def started_at(self) -> datetime | None:
        """The first job started, ISO 8601 UTC."""
        return utc(self.started) if self.started is not None else None

    @computed_field  # type: ignore[prop-decorator]
    @property
    def finished_at(self) -> datetime | None:
        """Succeeded, failed or canceled, ISO 8601 UTC."""
        return utc(self.finished) if self.finished is not None else None


class CalibrationSummary(BaseModel):
    """One line of the calibration listing."""

    id: str
    name: str
    status: CalibrationStatus
    created: float = Field(description="Unix time, s (created_at: the same in ISO 8601)")
    parameter_set_id: str | None = None

    @computed_field  # type: ignore[prop-decorator]
    @property
    def created_at(self) -> datetime:
        """Submitted, ISO 8601 UTC."""
        return utc(self.created)


class Calibration(BaseModel):
    """A calibration: status, progress, and the result once succeeded."""

    id: str
    name: str
    status: CalibrationStatus
    progress: Progress
    timings: Timings
    fem_reference_id: str
    fem_cached: bool = Field(description="the FEM reference was already stored at submission")
    load_cases: list[str] = Field(
        default_factory=list,
        description="the spec's load case names, in the order of the result's per-case lists",
    )
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
    model: str | None = Field(None, description="material model: linear or neo-hookean")
    element: str | None = Field(
        None,
        description="hex8 (the lattice's hexahedra) or tet10 (reference.mesh or mesh_id in "
        "10-node tetrahedra, read at the lattice nodes)",
    )
    residuals: list[float] | None = Field(
        None, description="(L,) final relative residual of each load case's solve"
    )
    load_steps: list[int] | None = Field(
        None, description="(L,) load steps per load case (neo-hookean; empty for linear)"
    )
    newton_iterations: list[list[int]] | None = Field(
        None, description="(L, steps) Newton iterations of each load step (neo-hookean)"
    )
    estimated_error: list[float] | None = Field(
        None,
        description="(L,) per load case (then validation case) the reference's estimated "
        "error, %: the relative change at the lattice nodes from its last refinement to the "
        "one before (reference.refine); null when not estimated",
    )
    refinements: int | None = Field(
        None, description="uniform refinements of the mesh it was solved on (0: as given)"
    )
    loads: str | None = Field(
        None,
        description="'nodal' (point loads at the lattice nodes) or 'spread' (each over its "
        "node's share of the solid)",
    )
    levels: list[dict[str, Any]] | None = Field(
        None,
        description="per level solved: refinements, fem_nodes, change (per case, %, from the "
        "level before), seconds, iterations (CG per case; empty for a direct solve)",
    )
    notes: list[str] | None = Field(
        None, description="a refinement the node budget refused, an error not estimated"
    )
    error: str | None = None
    nodes: list[list[float]] | None = Field(None, description="(N, 3) rest positions, m")
    displacements: list[list[list[float]]] | None = Field(
        None, description="(L, N, 3) nodal displacements per load case, m"
    )


class ParameterSet(ParameterSetRecord):
    """A stored (stiffness, d, depth) with its material, geometry summary, fit and provenance.

    The stored record's fields (:class:`store.records.ParameterSetRecord`, which the finalize
    job builds) under the REST names: ``damping`` (``d`` is still sent, outside the document)
    and ``created_at``.
    """

    damping: float = Field(description="nodal damping d, N s/m (meaningful only with dt)")
    d: SkipJsonSchema[float] = Field(description=f"damping: {OLD_D}")

    @computed_field  # type: ignore[prop-decorator]
    @property
    def created_at(self) -> datetime:
        """Stored, ISO 8601 UTC."""
        return utc(self.created)

    @model_validator(mode="before")
    @classmethod
    def _names(cls, data: Any) -> Any:
        return _old_name(data, "damping", "d")


class ParameterSetPage(BaseModel):
    items: list[ParameterSet]
    total: int


class KeyUsage(BaseModel):
    """One API key's use of its quotas (the key itself is never shown)."""

    owner: str = Field(description="the first 16 hex digits of the key's SHA-256 ('anonymous')")
    active: int = Field(description="calibrations queued or running")
    nodes_in_flight: int = Field(description="their lattice nodes")


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
    keys: list[KeyUsage] = Field(
        [], description="per API key with calibrations in flight, its use of the quotas"
    )
