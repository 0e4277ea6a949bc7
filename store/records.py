"""Reading and writing the project's records in Redis (no numerical code here).

Values are JSON or plain strings; nothing is pickled. Multi-key writes go through one
pipeline (MULTI/EXEC), and status changes that must not undo a cancel go through a WATCH
transaction on the calibration record.
"""

from __future__ import annotations

import json
import math
import sys
import time
from array import array
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from redis import Redis
from redis.client import Pipeline

from fpm.model.spec import Material, StiffnessMode, TransverselyIsotropicMaterial

from . import keys
from .status import TERMINAL, CalibrationStatus, FemStatus, Phase

Mapping = dict[Any, Any]
"""What redis-py's hset accepts (its stubs want a key type wider than str)."""


def _text(value: bytes | str | None) -> str | None:
    return value.decode() if isinstance(value, bytes) else value


def id_list(reply: Any) -> list[str]:
    """A list reply of ids (bytes) as str."""
    return [i.decode() for i in reply]


def decode_hash(raw: dict[Any, Any]) -> dict[str, str]:
    """A Redis hash reply with bytes keys and values as str -> str."""
    return {_text(k) or "": _text(v) or "" for k, v in raw.items()}


@dataclass
class CalibrationRecord:
    """The calibration record (hash ``keys.calibration(id)``).

    Attributes:
        id: calibration id.
        status, phase: see :mod:`store.status`.
        name: the spec's name.
        spec: the validated spec with every default filled in.
        spec_hash, fem_hash: content hashes (:mod:`store.hashing`).
        chains: number of annealing chains.
        created, started, finished: Unix times, s (0 = not yet).
        fem_cached: the FEM reference was already stored when this was submitted.
        error: why it failed ('' otherwise).
        result: the CalibrationResult as a dict once succeeded.
        parameter_set_id: the stored parameter set once succeeded.
    """

    id: str
    spec: dict[str, Any]
    spec_hash: str
    fem_hash: str
    chains: int
    status: CalibrationStatus = CalibrationStatus.QUEUED
    phase: Phase = Phase.QUEUED
    name: str = ""
    created: float = field(default_factory=time.time)
    started: float = 0.0
    finished: float = 0.0
    fem_cached: bool = False
    error: str = ""
    result: dict[str, Any] | None = None
    parameter_set_id: str = ""

    def to_hash(self) -> Mapping:
        """Flat str mapping for HSET."""
        out = {k: v for k, v in asdict(self).items() if k not in ("spec", "result")}
        out["status"] = self.status.value
        out["phase"] = self.phase.value
        out["fem_cached"] = int(self.fem_cached)
        out["spec"] = json.dumps(self.spec)
        out["result"] = json.dumps(self.result)
        return {k: str(v) for k, v in out.items()}

    @classmethod
    def from_hash(cls, raw: dict[str, str]) -> CalibrationRecord:
        return cls(
            id=raw["id"],
            spec=json.loads(raw["spec"]),
            spec_hash=raw["spec_hash"],
            fem_hash=raw["fem_hash"],
            chains=int(raw["chains"]),
            status=CalibrationStatus(raw["status"]),
            phase=Phase(raw["phase"]),
            name=raw.get("name", ""),
            created=float(raw["created"]),
            started=float(raw.get("started") or 0),
            finished=float(raw.get("finished") or 0),
            fem_cached=raw.get("fem_cached") == "1",
            error=raw.get("error", ""),
            result=json.loads(raw.get("result") or "null"),
            parameter_set_id=raw.get("parameter_set_id", ""),
        )


def get_calibration(redis: Redis, calibration_id: str) -> CalibrationRecord | None:
    """The record, or None if there is no such calibration."""
    raw = redis.hgetall(keys.calibration(calibration_id))
    return CalibrationRecord.from_hash(decode_hash(raw)) if raw else None


def calibration_page(
    redis: Redis, offset: int, limit: int, status: CalibrationStatus | None = None
) -> tuple[int, list[CalibrationRecord]]:
    """Calibrations newest first, ``limit`` from ``offset`` (only those of ``status`` when
    given), and how many there are in all."""
    if status is None:
        total = redis.zcard(keys.calibrations())
        ids = id_list(redis.zrevrange(keys.calibrations(), offset, offset + limit - 1))
        return total, get_calibrations(redis, ids)
    all_ids = id_list(redis.zrevrange(keys.calibrations(), 0, -1))
    matching = [r for r in get_calibrations(redis, all_ids) if r.status == status]
    return len(matching), matching[offset : offset + limit]


STAMP_FIELDS = ("status", "created", "finished", "parameter_set_id", "error", "result")
"""The record's fields a finished calibration's answer is made of besides its spec (which a
record never changes) and its progress reports (which end before it finishes)."""


def calibration_stamp(redis: Redis, calibration_id: str) -> tuple[str, ...] | None:
    """The record's :data:`STAMP_FIELDS` as stored (one read, no JSON decoded), or None if
    there is no such calibration: equal stamps, equal records."""
    values = redis.hmget(keys.calibration(calibration_id), list(STAMP_FIELDS))
    return None if values[0] is None else tuple(_text(v) or "" for v in values)


CalibrationView = tuple[
    CalibrationRecord, dict[int, dict[str, Any]], dict[str, Any] | None, tuple[str, ...]
]
"""(record, chain progress by chain, damping stage progress or None, stamp)."""


def get_calibration_view(redis: Redis, calibration_id: str) -> CalibrationView | None:
    """The record, its progress reports (per chain, and the damping stage's) and its stamp
    (:func:`calibration_stamp`, of the same read) in one round trip, or None if there is no
    such calibration."""
    pipe = redis.pipeline(transaction=False)
    pipe.hgetall(keys.calibration(calibration_id))
    pipe.hgetall(keys.calibration_progress(calibration_id))
    raw, raw_progress = pipe.execute()
    if not raw:
        return None
    chains, damping = split_progress(decode_hash(raw_progress))
    fields = decode_hash(raw)
    stamp = tuple(fields.get(f, "") for f in STAMP_FIELDS)
    return CalibrationRecord.from_hash(fields), chains, damping, stamp


def calibration_timings(redis: Redis) -> list[tuple[CalibrationStatus, float, float]]:
    """(status, started, finished) of every calibration (Unix times, s; 0 = not yet): one
    pipelined HMGET per calibration (about 10 ms for 10,000)."""
    pipe = redis.pipeline(transaction=False)
    for calibration_id in id_list(redis.zrange(keys.calibrations(), 0, -1)):
        pipe.hmget(keys.calibration(calibration_id), "status", "started", "finished")
    return [
        (CalibrationStatus(status.decode()), float(started or 0), float(finished or 0))
        for status, started, finished in pipe.execute()
        if status is not None
    ]


def evaluations_total(redis: Redis) -> int:
    """Annealing cost evaluations of every finished chain (a counter that only grows)."""
    return int(redis.get(keys.evaluations_total()) or 0)


def get_calibrations(redis: Redis, ids: Iterable[str]) -> list[CalibrationRecord]:
    """Several records in one round trip (missing ones are skipped)."""
    pipe = redis.pipeline(transaction=False)
    for calibration_id in ids:
        pipe.hgetall(keys.calibration(calibration_id))
    return [CalibrationRecord.from_hash(decode_hash(raw)) for raw in pipe.execute() if raw]


def get_progress(redis: Redis, calibration_id: str) -> dict[int, dict[str, Any]]:
    """Chain index -> latest progress report of that chain."""
    raw = decode_hash(redis.hgetall(keys.calibration_progress(calibration_id)))
    return split_progress(raw)[0]


def get_damping_progress(redis: Redis, calibration_id: str) -> dict[str, Any] | None:
    """The damping stage's latest progress report (None before it has reported)."""
    raw = redis.hget(keys.calibration_progress(calibration_id), keys.DAMPING_PROGRESS)
    return json.loads(raw) if raw else None


def split_progress(
    raw: dict[str, str],
) -> tuple[dict[int, dict[str, Any]], dict[str, Any] | None]:
    """A decoded progress hash as ({chain: report}, damping stage report or None)."""
    chains = {int(k): json.loads(v) for k, v in raw.items() if k.isdigit()}
    damping = raw.get(keys.DAMPING_PROGRESS)
    return chains, json.loads(damping) if damping else None


def write_calibration(pipe: Pipeline, record: CalibrationRecord) -> None:
    """Queue the writes of a new record: the hash, the listing, the spec-hash lookup."""
    pipe.hset(keys.calibration(record.id), mapping=record.to_hash())
    pipe.zadd(keys.calibrations(), {record.id: record.created})
    pipe.set(keys.calibration_by_spec(record.spec_hash), record.id)


def update_calibration(
    redis: Redis,
    calibration_id: str,
    fields: dict[str, Any],
    *,
    extra: Any = None,
) -> bool:
    """Set ``fields`` on a calibration unless it is already finished (e.g. canceled).

    ``extra(pipe)``, if given, queues more writes into the same MULTI/EXEC. Returns False
    (and writes nothing) when the record is missing or terminal.
    """
    key = keys.calibration(calibration_id)
    mapping = _flat_fields(fields)

    def apply(pipe: Pipeline) -> bool:
        status = _text(pipe.hget(key, "status"))
        if status is None or CalibrationStatus(status) in TERMINAL:
            pipe.unwatch()
            return False
        pipe.multi()
        pipe.hset(key, mapping=mapping)
        if extra is not None:
            extra(pipe)
        return True

    transaction: Any = redis.transaction  # its stub wants a callable returning None
    return bool(transaction(apply, key, value_from_callable=True))


def _flat_fields(fields: Mapping) -> Mapping:
    """Record fields as Redis hash strings: statuses by value, dicts, lists and None as JSON."""
    return {k: _flat(v) for k, v in fields.items()}


def _flat(value: Any) -> str:
    if isinstance(value, CalibrationStatus | FemStatus | Phase):
        return value.value
    if isinstance(value, dict | list) or value is None:
        return json.dumps(value)
    return str(value)


def get_fem_meta(redis: Redis, fem_hash: str) -> dict[str, str]:
    """The FEM reference's meta hash ({} if unknown): status, spec, n_nodes, error, ..."""
    return decode_hash(redis.hgetall(keys.fem_meta(fem_hash)))


def fem_status(redis: Redis, fem_hash: str) -> FemStatus | None:
    """The FEM reference's status, None if it was never submitted."""
    status = _text(redis.hget(keys.fem_meta(fem_hash), "status"))
    return FemStatus(status) if status else None


def has_fem_reference(redis: Redis, fem_hash: str) -> bool:
    return bool(redis.exists(keys.fem_reference(fem_hash)))


def update_fem_meta(redis: Redis, fem_hash: str, fields: Mapping) -> None:
    """Set fields of the FEM reference's meta hash (status, started, error, ...)."""
    redis.hset(keys.fem_meta(fem_hash), mapping=_flat_fields(fields))


RAW_REFERENCE = b"fpm-fem-reference/raw-1\n"
"""How a stored FEM reference's value starts: then its layout (the FemResult dict without
``nodes`` and ``displacements``, with their ``shapes``) as one line of JSON, then the arrays as
little-endian float64, nodes first. A value without it is the older form, the whole dict as
JSON (still read). At 93,705 nodes the JSON took 1.5 s to write and 0.9 s to read in every job
that read it; the raw arrays take milliseconds."""
ARRAYS = ("nodes", "displacements")


def save_fem_reference(
    redis: Redis, fem_hash: str, layout: dict[str, Any], arrays: bytes, meta: Mapping
) -> None:
    """Store a solved FEM reference (no expiry), ``layout`` and raw ``arrays`` as
    :data:`RAW_REFERENCE` says (:meth:`fpm.fem.solution.FemResult.to_stored`, or
    :func:`pack_reference`), with its meta fields, in one MULTI/EXEC."""
    pipe = redis.pipeline()
    pipe.set(keys.fem_reference(fem_hash), stored_reference(layout, arrays))
    pipe.hset(keys.fem_meta(fem_hash), mapping=_flat_fields(meta))
    pipe.execute()


def stored_reference(layout: dict[str, Any], arrays: bytes) -> bytes:
    """A reference's stored value (:data:`RAW_REFERENCE`)."""
    return RAW_REFERENCE + json.dumps(layout).encode() + b"\n" + arrays


def get_fem_arrays(redis: Redis, fem_hash: str) -> tuple[dict[str, Any], bytes] | None:
    """The stored reference as (layout, raw arrays) (:data:`RAW_REFERENCE`;
    :meth:`fpm.fem.solution.FemResult.from_stored` reads them), or None."""
    value = redis.get(keys.fem_reference(fem_hash))
    if not value:
        return None
    raw = value.encode() if isinstance(value, str) else bytes(value)
    if not raw.startswith(RAW_REFERENCE):
        return pack_reference(json.loads(raw))
    line_end = raw.index(b"\n", len(RAW_REFERENCE))
    return json.loads(raw[len(RAW_REFERENCE) : line_end]), raw[line_end + 1 :]


def get_fem_reference(redis: Redis, fem_hash: str) -> dict[str, Any] | None:
    """The stored FemResult dict, arrays as nested lists (the service's answer, backups), or
    None."""
    stored = get_fem_arrays(redis, fem_hash)
    return None if stored is None else unpack_reference(*stored)


def pack_reference(reference: dict[str, Any]) -> tuple[dict[str, Any], bytes]:
    """A FemResult dict whose ``nodes`` (N, 3) and ``displacements`` (L, N, 3) are nested
    lists, m, as (layout, raw arrays) (:data:`RAW_REFERENCE`)."""
    layout = {k: v for k, v in reference.items() if k not in ARRAYS}
    layout["shapes"] = {name: _shape(reference[name]) for name in ARRAYS}
    flat = array("d", (float(x) for name in ARRAYS for x in _flatten(reference[name])))
    if sys.byteorder != "little":
        flat.byteswap()
    return layout, flat.tobytes()


def unpack_reference(layout: dict[str, Any], arrays: bytes) -> dict[str, Any]:
    """The FemResult dict of :func:`pack_reference`'s (layout, raw arrays)."""
    flat = array("d")
    flat.frombytes(arrays)
    if sys.byteorder != "little":
        flat.byteswap()
    values = flat.tolist()
    reference = {k: v for k, v in layout.items() if k != "shapes"}
    start = 0
    for name in ARRAYS:
        shape = layout["shapes"][name]
        size = math.prod(shape)
        reference[name] = _nest(values[start : start + size], shape)
        start += size
    return reference


def _shape(nested: Any) -> list[int]:
    shape = []
    while isinstance(nested, list | tuple):
        shape.append(len(nested))
        nested = nested[0] if nested else None
    return shape


def _flatten(nested: Any) -> Iterable[Any]:
    if isinstance(nested, list | tuple):
        for item in nested:
            yield from _flatten(item)
    else:
        yield nested


def _nest(values: list[float], shape: list[int]) -> Any:
    if len(shape) <= 1:
        return values
    if not shape[0]:
        return []
    size = len(values) // shape[0]
    return [_nest(values[i * size : (i + 1) * size], shape[1:]) for i in range(shape[0])]


def save_mesh(redis: Redis, mesh_id: str, mesh: dict[str, Any]) -> bool:
    """Store an uploaded tetrahedral mesh (canonical, :func:`store.hashing.canonical_mesh`)
    under its content hash, no expiry; True when it was new (a second upload is a no-op)."""
    return bool(redis.set(keys.mesh(mesh_id), json.dumps(mesh), nx=True))


def has_mesh(redis: Redis, mesh_id: str) -> bool:
    return bool(redis.exists(keys.mesh(mesh_id)))


def get_mesh(redis: Redis, mesh_id: str) -> dict[str, Any] | None:
    """The uploaded mesh ``{"nodes": [[x, y, z], ...], "tetrahedra": [[i, j, k, l], ...]}``,
    or None."""
    raw = redis.get(keys.mesh(mesh_id))
    return json.loads(raw) if raw else None


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


class ParameterSetRecord(BaseModel):
    """A stored parameter set (string ``keys.parameter_set(id)``, JSON): the fitted
    (stiffness, d, depth) with its material, geometry summary, fit and provenance.

    The one definition: the finalize job builds it, and the service's answer
    (``service.schemas.ParameterSet``) derives from it, adding only the REST names (``damping``
    beside ``d``, ``created_at``). Reads return the stored dict, since a set stored by an
    older version may lack fields (the service answers 410 for it).
    """

    model_config = ConfigDict(extra="allow")

    id: str
    created: float = Field(description="Unix time, s (created_at: the same in ISO 8601)")
    name: str
    k: float = Field(description="stiffness of the axis family (the one k for 'single'), N/m")
    stiffness: dict[str, float] = Field(description="k per spring family present, N/m")
    stiffness_mode: StiffnessMode = Field(description="the spec's fpm.stiffness")
    volume_stiffness: float | None = Field(
        None,
        description="kappa, Pa: every cell's volume stiffness ('families+volume'; None for the "
        "spring-only models)",
    )
    field: dict[str, Any] | None = Field(
        None,
        description="fpm.stiffness 'field': the per-cell stiffness field and its figures beside "
        "the four-parameter fit's (the calibration result's field; the export applies it when "
        "returned)",
    )
    d: float = Field(description="nodal damping, N s/m (meaningful only with dt)")
    d_min: float | None = Field(description="smallest d that still settles (two-stage), N s/m")
    depth: int
    dt: float = Field(description="the time step the set was fitted at, s")
    stiffness_scale: list[float] = Field(description="per-axis stiffness factors (sx, sy, sz)")
    material: Material | TransverselyIsotropicMaterial = Field(
        description="the spec's material (its model only if not linear)"
    )
    geometry: GeometrySummary
    relative_discrepancy: list[float] = Field(
        description="per load case, % (scale-free; the headline figure)"
    )
    loaded_discrepancy: list[float] = Field(description="per load case, loaded nodes only, %")
    discrepancy_h: list[float] = Field(
        description="per load case, % of h (the paper's unit; read it beside the relative figure)"
    )
    validation_cases: list[str] = Field([], description="the validation cases' names")
    validation_relative_discrepancy: list[float] = Field(
        [],
        description="per validation case (never in the cost), % at the fitted parameters: the "
        "honest figure",
    )
    validation_discrepancy_h: list[float] = Field([], description="per validation case, % of h")
    compliance_ratio: list[float | None] = Field(
        [],
        description="per load case, the load compliance ratio (the model's sum_i f_i . u_i over "
        "its loaded nodes over the reference's: 1.0 feels the reference's stiffness, 1.5 is 1.5 "
        "times too soft); empty in sets stored before it",
    )
    validation_compliance_ratio: list[float | None] = Field(
        [], description="the same per validation case"
    )
    verdict: dict[str, Any] | None = Field(
        None,
        description="the fit's verdict (fpm.fitting.result.Verdict: grade 'good', 'fair' or "
        "'poor', its basis, floor, bounds and causes); null in sets stored before it",
    )
    node_mass: dict[str, float] = Field(description="lumped node masses: min, max, mean, total, kg")
    warnings: list[str] = []
    cost: float = Field(description="Eq. (2) of the last dynamic run, m")
    provenance: Provenance


def get_parameter_set(redis: Redis, parameter_set_id: str) -> dict[str, Any] | None:
    """A stored parameter set (:class:`ParameterSetRecord`'s fields), or None."""
    raw = redis.get(keys.parameter_set(parameter_set_id))
    return json.loads(raw) if raw else None


def list_parameter_sets(redis: Redis) -> list[dict[str, Any]]:
    """Every stored parameter set, newest first."""
    ids = id_list(redis.zrevrange(keys.parameter_sets(), 0, -1))
    if not ids:
        return []
    raws = redis.mget([keys.parameter_set(i) for i in ids])
    return [json.loads(raw) for raw in raws if raw]


def parameter_set_count(redis: Redis) -> int:
    return int(redis.zcard(keys.parameter_sets()))


def write_parameter_set(pipe: Pipeline, parameter_set: ParameterSetRecord) -> None:
    """Queue storing a parameter set once: a retry with the same id changes nothing."""
    raw = json.dumps(parameter_set.model_dump())
    pipe.set(keys.parameter_set(parameter_set.id), raw, nx=True)
    pipe.zadd(keys.parameter_sets(), {parameter_set.id: parameter_set.created}, nx=True)
