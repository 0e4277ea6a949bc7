"""The problem spec: one pydantic schema for the CLI, the worker and the service.

A spec names a material, a solid (geometry + spring connectivity), the fixed nodes, the load
cases, and the FPM and annealing settings. All quantities are SI (m, N, Pa, kg/m^3, s).
Validation here is what can be checked without building the solid; checks that need the nodes
(a point with no node, a node index out of range, a box with no node) happen in
:func:`fpm.model.problem.load_problem`, which raises the same kind of error with the field's
location.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

MODEL_VERSION = "2026.12.08"
"""Version of the numerics behind a result; bump it whenever a change alters fitted values.
It is part of a calibration's identity, so a resubmitted spec is not answered from results
that older numerics computed."""
FEM_VERSION = "2026.12.08"
"""Version of the FEM reference's numerics; bump it whenever a change alters FEM displacements.
It is part of a stored reference's identity (references are kept without expiry), so new
calibrations are never served a reference that older FEM numerics computed."""
EXPORT_VERSION = "2026.12.05"
"""Version of the export formats (:mod:`fpm.io.export`); bump it whenever a change alters an
export's bytes. Part of a cached export's identity (:func:`store.hashing.export_hash`), so the
service never hands out an export written by older code."""

Vector3 = tuple[float, float, float]
Connectivity = Literal["axis", "axis+face", "full"]
Face = Literal["x-", "x+", "y-", "y+", "z-", "z+"]
FACES: tuple[str, ...] = get_args(Face)
"""The box faces a selector can name (e.g. {"face": "z-"})."""
UNITS_HINT = "E is in Pa (5 kPa = 5000), lengths in m, forces in N"
"""The units a spec is written in, as error messages remind a user who mixed them up."""


class _Strict(BaseModel):
    """Base: unknown fields are errors (a typo must not be silently ignored); no NaN or inf."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


MaterialModel = Literal["linear", "neo-hookean"]
StiffnessMode = Literal["families+volume", "single", "families", "field"]
STIFFNESS_MODES: tuple[str, ...] = get_args(StiffnessMode)
VOLUME_MODES = ("families+volume", "field")
"""The stiffness modes with the volume term and springs assembled from cells (theta: the
families, then kappa); ``field`` adds per-cell factors on top
(:func:`fpm.model.stiffness.field_stiffness`). Here, so that the store, which sees only the
spec, knows which calibrations build stage 1's reduced basis."""
MAX_DT = 1e-3
"""dt 'auto' is at most this, s (a haptic 1 kHz loop)."""


def lame_constants(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda), Pa, of E (Pa) and nu: mu = E / (2 (1 + nu)),
    lambda = E nu / ((1 + nu)(1 - 2 nu))."""
    e, nu = youngs_modulus, poisson_ratio
    return e / (2 * (1 + nu)), e * nu / ((1 + nu) * (1 - 2 * nu))


class Material(_Strict):
    """Isotropic elastic constants (paper Table 1) and the FEM reference's material model.

    ``model``: ``"linear"`` (small-strain linear elasticity, the paper's, default) or
    ``"neo-hookean"`` (compressible neo-Hookean, large deformation: :mod:`fpm.fem.hyperelastic`),
    both from the same E and nu. ``"linear"`` is left out of dumps, so the identity (content
    hash) of a linear spec is what it was before the field existed.
    """

    youngs_modulus: float = Field(gt=0, description="Young's modulus E, Pa")
    poisson_ratio: float = Field(
        gt=-1.0, lt=0.5, description="Poisson's ratio, in (-1, 0.5) for a stable solid"
    )
    density: float = Field(gt=0, description="mass density, kg/m^3 (lumped into node masses)")
    model: MaterialModel = Field(
        "linear",
        description="FEM reference: 'linear' (small-strain linear elasticity, the paper's) or "
        "'neo-hookean' (compressible neo-Hookean, large deformation, Lame constants from E, nu)",
        exclude_if=lambda v: v == "linear",
    )
    type: Literal["isotropic"] = Field(
        "isotropic",
        description="'isotropic' (these fields) or 'transversely-isotropic' (see "
        "TransverselyIsotropicMaterial)",
        exclude_if=lambda v: v == "isotropic",
    )
    regions: list[MaterialRegion] = Field(
        [],
        description="parts of the solid of another material, in order (a later region takes "
        "the cells it shares with an earlier one); the rest is this material. Linear FEM and "
        "fpm.stiffness 'families+volume' only",
        exclude_if=lambda v: not v,
    )

    @field_validator("regions")
    @classmethod
    def _distinct_names(cls, v: list[MaterialRegion]) -> list[MaterialRegion]:
        names = region_names(v)
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ValueError(f"region names must differ (repeated: {', '.join(repeated)})")
        return v


REGION_SELECTOR_FIELDS = ("box", "sphere", "tag")
"""The ways a :class:`RegionSelector` names part of the solid; give exactly one."""
BASE_REGION = "base"
"""Name of the cells no region takes (the spec's own material) among the fitted regions."""


class Sphere(_Strict):
    """A ball: centre (m) and radius (m)."""

    centre: Vector3
    radius: float = Field(gt=0, description="m")


class RegionSelector(_Strict):
    """Part of the solid: exactly one of ``box`` (an axis-aligned box, m), ``sphere`` (a ball)
    or ``tag`` (the tetrahedra of the reference mesh whose cell-data tag is this integer,
    ``reference.mesh.tags`` or an uploaded mesh's). A lattice cell belongs to it when its centre
    does (for a tag: when its centre lies in such a tetrahedron); an FEM element when its
    centroid does (hexahedra) or when it is inside / carries the tag (tetrahedra)."""

    box: tuple[Vector3, Vector3] | None = Field(
        None, description="[[x0,y0,z0],[x1,y1,z1]], m, low corner first"
    )
    sphere: Sphere | None = None
    tag: int | None = Field(None, description="cell-data tag of the tetrahedral reference mesh")

    @field_validator("box")
    @classmethod
    def _ordered(cls, v: tuple[Vector3, Vector3] | None) -> tuple[Vector3, Vector3] | None:
        if v is not None and any(lo > hi for lo, hi in zip(v[0], v[1], strict=True)):
            raise ValueError("give the low corner first: [[x0,y0,z0],[x1,y1,z1]]")
        return v

    @model_validator(mode="after")
    def _exactly_one(self) -> RegionSelector:
        given = [n for n in REGION_SELECTOR_FIELDS if getattr(self, n) is not None]
        if len(given) != 1:
            raise ValueError(
                f"give exactly one of {', '.join(REGION_SELECTOR_FIELDS)} "
                f"(got {', '.join(given) or 'none'})"
            )
        return self


class MaterialRegion(_Strict):
    """A part of the solid of another isotropic material (``material.regions``): E, nu and
    density default to the spec's material. Each region gets its own fitted parameters
    (families and kappa), reported under its ``name`` (default ``region<i>``)."""

    name: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.+-][A-Za-z0-9_ .+-]*$",
        description="letters, digits, space, _ . + - (not 'base': the cells of no region)",
    )
    selector: RegionSelector
    youngs_modulus: float | None = Field(None, gt=0, description="Pa (default: the material's)")
    poisson_ratio: float | None = Field(
        None, gt=-1.0, lt=0.5, description="default: the material's"
    )
    density: float | None = Field(None, gt=0, description="kg/m^3 (default: the material's)")

    @field_validator("name")
    @classmethod
    def _not_base(cls, v: str | None) -> str | None:
        if v == BASE_REGION:
            raise ValueError(f"'{BASE_REGION}' names the cells of no region: choose another name")
        return v


def region_names(regions: list[MaterialRegion]) -> list[str]:
    """Each region's name: its own, or ``region<i>`` (i its index in ``material.regions``)."""
    return [r.name if r.name is not None else f"region{i}" for i, r in enumerate(regions)]


class TransverselyIsotropicMaterial(_Strict):
    """A transversely isotropic solid (fibres, muscle): isotropic in the plane normal to
    ``axis``, with its own modulus along it (:mod:`fpm.model.anisotropy` has the tensor).

    The compliance must be positive definite: with positive moduli and -1 < nu_t < 1 that is
    ``1 - nu_t - 2 nu_a^2 E_t / E_a > 0`` (checked at ``poisson_ratio_axial``). Linear FEM
    only; the lattice fits families+volume and the axial scale of its springs. ``youngs_modulus``
    and ``poisson_ratio`` read the transverse (in-plane) constants, which set the scale of the
    fit's bounds.
    """

    type: Literal["transversely-isotropic"]
    axis: Vector3 = Field(description="the material axis (any length > 0)")
    youngs_modulus_axial: float = Field(gt=0, description="E_a, Pa: along the axis")
    youngs_modulus_transverse: float = Field(gt=0, description="E_t, Pa: across the axis")
    poisson_ratio_transverse: float = Field(
        gt=-1.0,
        lt=1.0,
        description="nu_t: a stretch across the axis narrows the other in-plane direction by "
        "nu_t times the stretch",
    )
    shear_modulus_axial: float = Field(
        gt=0, description="G_a, Pa: shear in the planes that contain the axis"
    )
    poisson_ratio_axial: float = Field(
        description="nu_a: a stretch along the axis narrows every in-plane direction by nu_a "
        "times the stretch"
    )
    density: float = Field(gt=0, description="mass density, kg/m^3 (lumped into node masses)")
    model: Literal["linear"] = Field(
        "linear",
        description="FEM reference: 'linear' only (the neo-Hookean reference is isotropic)",
        exclude_if=lambda v: v == "linear",
    )
    regions: list[MaterialRegion] = Field(
        [],
        description="not for a transversely isotropic material (regions are isotropic): leave "
        "empty",
        exclude_if=lambda v: not v,
        max_length=0,
    )

    @field_validator("axis")
    @classmethod
    def _nonzero_axis(cls, v: Vector3) -> Vector3:
        if math.hypot(*v) == 0:
            raise ValueError("the axis must not be zero")
        return v

    @field_validator("poisson_ratio_axial")
    @classmethod
    def _positive_definite(cls, v: float, info: ValidationInfo) -> float:
        e_a = info.data.get("youngs_modulus_axial")
        e_t = info.data.get("youngs_modulus_transverse")
        nu_t = info.data.get("poisson_ratio_transverse")
        if e_a is None or e_t is None or nu_t is None:
            return v  # their own errors
        margin = 1.0 - nu_t - 2.0 * v * v * e_t / e_a
        if not margin > 0:
            raise ValueError(
                "the stiffness tensor is not positive definite: need 1 - nu_t - 2 nu_a^2 E_t / "
                f"E_a > 0, here {margin:.4g} (|nu_a| below "
                f"{math.sqrt(max(1.0 - nu_t, 0.0) * e_a / (2.0 * e_t)):.4g} for these E_a, E_t "
                "and nu_t)"
            )
        return v

    @property
    def youngs_modulus(self) -> float:
        """E_t, Pa: the in-plane modulus (the scale of the fit's bounds)."""
        return self.youngs_modulus_transverse

    @property
    def poisson_ratio(self) -> float:
        """nu_t, the in-plane Poisson's ratio."""
        return self.poisson_ratio_transverse


MATERIAL_TYPES = ("isotropic", "transversely-isotropic")
"""``material.type``: :class:`Material` (the default) or :class:`TransverselyIsotropicMaterial`."""


def validate_material(value: Any) -> Material | TransverselyIsotropicMaterial:
    """``material`` by its ``type`` (absent: isotropic), errors located in that model's fields."""
    if isinstance(value, Material | TransverselyIsotropicMaterial):
        return value
    kind = value.get("type", "isotropic") if isinstance(value, dict) else "isotropic"
    if kind not in MATERIAL_TYPES:
        raise ValidationError.from_exception_data(
            "Material",
            [
                InitErrorDetails(
                    type=PydanticCustomError(
                        "material_type",
                        "unknown material type '{kind}': use 'isotropic' (the default) or "
                        "'transversely-isotropic'",
                        {"kind": str(kind)},
                    ),
                    loc=("type",),
                    input=kind,
                )
            ],
        )
    if kind == "transversely-isotropic":
        return TransverselyIsotropicMaterial.model_validate(value)
    return Material.model_validate(value)


class BoxGeometry(_Strict):
    """A rectangular block meshed as a regular lattice of nodes[0] x nodes[1] x nodes[2] nodes."""

    type: Literal["box"] = "box"
    size: tuple[float, float, float] = Field(description="edge lengths, m")
    nodes: tuple[int, int, int] = Field(description="nodes along x, y, z (each at least 2)")
    origin: Vector3 = (0.0, 0.0, 0.0)
    connectivity: Connectivity = "full"

    @field_validator("size")
    @classmethod
    def _positive_size(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0:
            raise ValueError("every edge length must be > 0")
        return v

    @field_validator("nodes")
    @classmethod
    def _two_nodes(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        if min(v) < 2:
            raise ValueError("need at least 2 nodes along each axis")
        return v


class VoxelGeometry(_Strict):
    """An occupancy grid: ``occupancy[i][j][k]`` true fills the cell i (x), j (y), k (z)."""

    type: Literal["voxels"] = "voxels"
    occupancy: list[list[list[bool]]] = Field(description="cells along x, y, z; 1 = solid")
    spacing: tuple[float, float, float] = Field(description="cell edge lengths, m")
    origin: Vector3 = (0.0, 0.0, 0.0)
    connectivity: Connectivity = "full"

    @field_validator("spacing")
    @classmethod
    def _positive_spacing(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0:
            raise ValueError("every spacing must be > 0")
        return v

    @field_validator("occupancy")
    @classmethod
    def _rectangular(cls, v: list[list[list[bool]]]) -> list[list[list[bool]]]:
        if not v or not v[0] or not v[0][0]:
            raise ValueError("occupancy must be a non-empty 3-D grid")
        ny, nz = len(v[0]), len(v[0][0])
        if any(len(p) != ny or any(len(r) != nz for r in p) for p in v):
            raise ValueError("occupancy must be rectangular (every row the same length)")
        if not any(c for p in v for r in p for c in r):
            raise ValueError("occupancy has no solid cell")
        return v


class MeshGeometry(_Strict):
    """Explicit nodes and 8-node hexahedra (node order: see :mod:`fpm.model.hexahedron`)."""

    type: Literal["mesh"] = "mesh"
    nodes: list[Vector3] = Field(min_length=8, description="node coordinates, m")
    hexahedra: list[tuple[int, int, int, int, int, int, int, int]] = Field(min_length=1)
    connectivity: Connectivity = "full"


class NetworkGeometry(_Strict):
    """A mass-spring network given directly (surface models, paper Fig. 4a-d). No FEM."""

    type: Literal["network"] = "network"
    nodes: list[Vector3] = Field(min_length=2, description="node coordinates, m")
    springs: list[tuple[int, int]] = Field(min_length=1, description="node index pairs")
    masses: float | list[float] = Field(description="node mass, kg: one for all, or one per node")

    @field_validator("masses")
    @classmethod
    def _positive_masses(cls, v: float | list[float]) -> float | list[float]:
        if min(v if isinstance(v, list) else [v]) <= 0:
            raise ValueError("every node mass must be > 0")
        return v


Geometry = Annotated[
    BoxGeometry | VoxelGeometry | MeshGeometry | NetworkGeometry, Field(discriminator="type")
]


SELECTOR_FIELDS = ("face", "node", "at", "nearest", "box")
"""The ways a :class:`Selector` (and a :class:`Force`) names nodes; give exactly one."""


class Selector(_Strict):
    """Selects nodes: exactly one of ``face``, ``node``, ``at``, ``nearest``, ``box``.

    - ``node``: one node by index;
    - ``at``: the node at a point (it must lie within 1e-3 h of a node; else an error);
    - ``nearest``: the node nearest a point, however far (the distance is reported in
      :attr:`fpm.model.problem.Problem.notes`): for points read off a picture or another mesh;
    - ``face``: every node on that side of the solid's bounding box;
    - ``box``: every node inside an axis-aligned box (a box that holds no node is an error).
    """

    face: Face | None = Field(
        None, description="all nodes on that side of the solid's bounding box"
    )
    node: int | None = Field(None, ge=0, description="a node index")
    at: Vector3 | None = Field(None, description="the node at this point, m")
    nearest: Vector3 | None = Field(
        None, description="the node nearest this point, m (its distance is reported)"
    )
    box: tuple[Vector3, Vector3] | None = Field(
        None, description="all nodes inside [[x0,y0,z0],[x1,y1,z1]], m"
    )

    @field_validator("box")
    @classmethod
    def _ordered_corners(cls, v: tuple[Vector3, Vector3] | None) -> tuple[Vector3, Vector3] | None:
        if v is not None and any(lo > hi for lo, hi in zip(v[0], v[1], strict=True)):
            raise ValueError(
                "give the low corner first: [[x0,y0,z0],[x1,y1,z1]] with x0 <= x1, y0 <= y1, "
                "z0 <= z1"
            )
        return v

    @model_validator(mode="after")
    def _exactly_one(self) -> Selector:
        given = [n for n in SELECTOR_FIELDS if getattr(self, n) is not None]
        if len(given) != 1:
            raise ValueError(
                f"give exactly one of {', '.join(SELECTOR_FIELDS)} "
                f"(got {', '.join(given) or 'none'})"
            )
        return self

    @property
    def kind(self) -> str:
        """Which selector field is given (``"face"``, ``"node"``, ...)."""
        return next(n for n in SELECTOR_FIELDS if getattr(self, n) is not None)

    @property
    def single(self) -> bool:
        """True if it names one node (``node``, ``at``, ``nearest``)."""
        return self.face is None and self.box is None


class Force(Selector):
    """A constant force, N, on the nodes of one selector (``node``, ``at``, ``nearest``,
    ``face`` or ``box``: exactly one).

    On a selector of several nodes, ``vector`` goes to each node, so the total force is
    ``vector`` times the number of nodes; with ``"distribute": true`` the vector is split
    evenly over them instead (a patch load: the total force is ``vector``). Fixed nodes among
    a face's or box's nodes take no share (they are reported in
    :attr:`fpm.model.problem.Problem.notes`); a force on a single fixed node, or on a selection that
    is all fixed, is an error.
    """

    vector: Vector3 = Field(description="force, N (per node, or in total with distribute)")
    distribute: bool = Field(
        False,
        description="split vector evenly over the selected nodes (total force = vector); "
        "false: every selected node gets vector",
    )


class LoadCase(_Strict):
    """A set of constant nodal forces applied together, from rest (forces on the same node add
    up)."""

    name: str | None = None
    forces: list[Force] = Field(min_length=1)


class FpmSettings(_Strict):
    """FPM settings (paper Sec. 3; physics.md)."""

    depth: int | Literal["auto"] = Field(
        "auto",
        description="penetration depth in layers; 'auto' = the smallest depth whose Eq. 2 cost "
        "at the stiffness fitted at full depth is within auto_depth_tolerance of full depth's",
    )
    auto_depth_tolerance: float = Field(
        0.01,
        ge=0,
        le=1,
        description="depth 'auto': allowed relative rise of the cost over full depth's (0.01 = "
        "the relative discrepancy may grow by 1% of itself); larger trades realism for speed",
    )
    stiffness: StiffnessMode = Field(
        "families+volume",
        description="'families+volume' (the default where the lattice has cells with face "
        "diagonals, else 'single'): one k per spring family, springs assembled from cells, and "
        "a volume stiffness kappa per cell (Pa): can be any isotropic solid with nu >= 1/4; "
        "'single': one k for every spring (the paper's model); 'families': one k per spring "
        "family present (axis, face diagonal, body diagonal); 'field': families+volume, then a "
        "per-cell factor on the springs and on kappa fitted by adjoint gradients, smoothed "
        "between neighbouring cells by a weight chosen by cross-validation (one force pattern "
        "left out at a time), returned only where it predicts the left-out loads better than "
        "the four numbers (needs two or more load_cases; two-stage method)",
    )
    dt: float | Literal["auto"] = Field(
        "auto",
        description="time step, s, or 'auto' (default): half the lattice's stability estimate "
        "at the fitted stiffness, at most 1 ms (a haptic 1 kHz loop)",
    )
    max_steps: int | Literal["auto"] = Field(
        "auto",
        description="steps per load case before a run gives up (a cap: the result reports the "
        "steps each load case took and the cap, max_steps), 1 to 1,000,000, or 'auto' "
        "(default): three times the steps the lattice's slowest modes predict at the fitted d, "
        "at least 1,000 (20,000 where nothing predicts it, e.g. the paper method)",
    )
    settle_distance: float = Field(
        0.01,
        gt=0,
        lt=1,
        description="settled when the run's estimated distance from its static equilibrium "
        "(the 2-norm of its unbalanced nodal forces over the stiffness of the lattice's "
        "softest modes) is below this times the 2-norm of its displacements: default 0.01, "
        "within 1% of the static equilibrium (the estimate is a bound; measured 0.03-0.1% on "
        "organs of 4.6k and 19.7k nodes); scale-free, unlike settle_tolerance. Not used "
        "where settle_tolerance is named, nor by the paper method",
    )
    settle_tolerance: float | None = Field(
        None,
        ge=0,
        description="the force criterion instead of settle_distance: settled when the largest "
        "unbalanced nodal force in a sweep is below this times the largest applied nodal force "
        "(0 = never settle). None (default): settle_distance, or 1e-5 for the paper method "
        "and a lattice that is a mechanism at rest. Not scale-free: the same tolerance stops "
        "further from rest on a finer lattice",
    )
    stiffness_scale: Vector3 = Field(
        (1.0, 1.0, 1.0),
        description="per-axis stiffness factors (sx, sy, sz); a spring along unit vector e gets "
        "k * (sx ex^2 + sy ey^2 + sz ez^2) (paper Fig. 5)",
    )
    gravity: Vector3 = Field((0.0, 0.0, 0.0), description="m/s^2; the paper ignores gravity")

    @field_validator("dt")
    @classmethod
    def _positive_dt(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not v > 0:
            raise ValueError("dt must be > 0 (s) or 'auto'")
        return v

    @field_validator("max_steps")
    @classmethod
    def _max_steps_range(cls, v: int | str) -> int | str:
        if not isinstance(v, str) and not 1 <= v <= 1_000_000:
            raise ValueError("max_steps must be 1 to 1,000,000 or 'auto'")
        return v

    @field_validator("depth")
    @classmethod
    def _depth_nonneg(cls, v: int | str) -> int | str:
        if isinstance(v, int) and v < 0:
            raise ValueError("depth must be >= 0 or 'auto'")
        return v

    @field_validator("stiffness_scale")
    @classmethod
    def _positive_scale(cls, v: Vector3) -> Vector3:
        if min(v) <= 0:
            raise ValueError("stiffness factors must be > 0")
        return v


class Bounds(_Strict):
    """Search box for the annealer; None = derived (see :mod:`fpm.fitting.bounds`)."""

    k: tuple[float, float] | None = Field(None, description="spring stiffness range, N/m")
    d: tuple[float, float] | None = Field(None, description="nodal damping range, N s/m")

    @field_validator("k", "d")
    @classmethod
    def _ordered(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not 0 < v[0] < v[1]:
            raise ValueError("need 0 < low < high")
        return v


DEFAULT_T_FINAL = {"paper": 2e-4, "two-stage": 2e-3}


class AnnealingSettings(_Strict):
    """Simulated annealing settings (paper Sec. 4.2-4.3).

    Temperatures and ``c_max`` are in units of the reference cost (the cost of an FPM that does
    not move at all, i.e. the summed FEM displacement): a scale-free schedule that works for any
    material. Lundy-Mees cooling T <- T / (1 + beta T), one move per temperature, so a chain
    makes about (1/t_final - 1/t_initial) / beta moves.

    ``t_final`` defaults by method: 2e-4 for ``paper`` (151 moves, the joint (k, d) search on
    dynamic runs) and 2e-3 for ``two-stage`` (15 moves: its stage 1 searches 1-3 stiffness
    parameters of a smooth cost, where the anneal only has to find the basin and the bounded
    polish that follows resolves the optimum).
    """

    method: Literal["two-stage", "paper"] = Field(
        "two-stage",
        description="'two-stage': anneal the stiffness on static equilibria, then find the "
        "fastest-settling d; 'paper': anneal (k, d) jointly on dynamic runs (paper Sec. 4.3)",
    )
    seed: int = Field(0, ge=0)
    chains: int = Field(2, ge=1, le=64, description="independent chains; the best one wins")
    t_initial: float = Field(0.05, gt=0)
    t_final: float = Field(
        DEFAULT_T_FINAL["two-stage"], gt=0, description="default 2e-4 for paper, 2e-3 two-stage"
    )
    beta: float = Field(33.0, gt=0)
    c_max: float = Field(2.0, gt=0, description="reject at once a candidate costing more")
    bounds: Bounds = Field(default_factory=Bounds)

    @model_validator(mode="before")
    @classmethod
    def _default_t_final(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("t_final") is None:
            paper = data.get("method") == "paper"  # a bad method is the field's own error
            data = {**data, "t_final": DEFAULT_T_FINAL["paper" if paper else "two-stage"]}
        return data

    @model_validator(mode="after")
    def _cooling(self) -> AnnealingSettings:
        if self.t_final >= self.t_initial:
            raise ValueError("t_final must be below t_initial")
        moves = lundy_mees_moves(self.t_initial, self.t_final, self.beta)
        if moves > 1e6:
            raise ValueError(f"this schedule makes {moves:.3g} moves per chain (limit 1e6)")
        return self

    @property
    def moves(self) -> int:
        """Moves per chain implied by the cooling schedule (:func:`lundy_mees_moves`)."""
        return lundy_mees_moves(self.t_initial, self.t_final, self.beta)


MOVES_CAP = 1 << 62
""":func:`lundy_mees_moves` saturates here (a schedule this long is refused anyway)."""


def lundy_mees_moves(t_initial: float, t_final: float, beta: float) -> int:
    """Moves of a Lundy-Mees chain, one per temperature: T_{n+1} = T_n / (1 + beta T_n) makes
    1/T grow by beta per move, from 1/t_initial until T falls below t_final. (The one home of
    this formula: the spec's limits and moves, and the annealer's schedule, use it.)"""
    moves = (1 / t_final - 1 / t_initial) / beta
    return math.floor(moves) + 1 if moves < MOVES_CAP else MOVES_CAP  # beta 5e-324: inf


Integration = Literal["selective", "full"]


NodeIndex = Annotated[int, Field(ge=0, lt=2**31)]
"""A node index of a tetrahedral mesh (its range is checked against the nodes later)."""


class ReferenceMesh(_Strict):
    """A tetrahedral mesh of the solid for the FEM reference (10-node tetrahedra built on it:
    :mod:`fpm.fem.tet10`). Nodes in m, tetrahedra as 4 node indices (0-based) with positive
    volume (corner 3 on the positive side of face 0-1-2). Indices in range, distinct corners,
    and no inverted or degenerate tetrahedron are checked in :func:`fpm.model.problem.load_problem`
    (errors at ``reference.mesh.tetrahedra.<element>``). ``tags``: optional cell data, one
    integer per tetrahedron, that ``material.regions`` selectors name."""

    nodes: list[Vector3] = Field(min_length=4, description="node coordinates, m")
    tetrahedra: list[tuple[NodeIndex, NodeIndex, NodeIndex, NodeIndex]] = Field(
        min_length=1, description="4 node indices (0-based) per tetrahedron, positive volume"
    )
    tags: list[int] | None = Field(
        None,
        description="cell data: an integer tag per tetrahedron (e.g. Gmsh's physical group), "
        'for material.regions selectors {"tag": t}; null = none',
        exclude_if=lambda v: v is None,
    )

    @field_validator("tags")
    @classmethod
    def _one_per_tetrahedron(cls, v: list[int] | None, info: ValidationInfo) -> list[int] | None:
        tetrahedra = info.data.get("tetrahedra")
        if v is not None and tetrahedra is not None and len(v) != len(tetrahedra):
            raise ValueError(f"need one tag per tetrahedron ({len(tetrahedra)}), got {len(v)}")
        return v


MAX_REFINE = 6
"""reference.refine: at most this many uniform refinements (8^6 = 262,144 times the elements)."""


MESH_ID_PATTERN = r"^[0-9a-f]{64}$"
"""A mesh id: the sha256 hex digest the service's ``POST /v1/meshes`` returned."""


class ReferenceSettings(_Strict):
    """The FEM reference's discretisation (docs/physics.md, *The FEM reference*).

    ``integration``: how the FEM's 8-node hexahedra are integrated (linear and neo-Hookean).

    - ``"selective"`` (default): selective reduced integration, free of volumetric locking
      near nu = 1/2: the deviatoric (shear) part of C at the 2x2x2 Gauss points, the
      volumetric part (bulk modulus) on the element's mean dilatation, which is one-point
      integration at the centre on a parallelepiped. For the linear hexahedron this is
      exactly B-bar with the mean dilatation (Hughes 1980).
    - ``"full"``: 2x2x2 Gauss integration of all of C (the paper's element; it locks as nu
      approaches 1/2: 10% too stiff at nu 0.45 on the paper's cube). The paper's examples
      name it, so Table 1 is reproduced exactly.

    The neo-Hookean reference follows the same choice: ``"selective"`` is the decoupled
    neo-Hookean solid with its volume term on each element's mean dilatation (the large-strain
    B-bar, :class:`fpm.fem.neo_hookean.MeanDilatationNeoHookean`), ``"full"`` the compressible
    one at 2x2x2 points (it locks as the linear ``"full"`` does).

    ``mesh`` / ``mesh_id``: the solid's own tetrahedral mesh (inline, or the id of one uploaded
    to the service): the linear reference is then solved on it with 10-node tetrahedra and read
    at the lattice's nodes (:mod:`fpm.fem.tet10`); ``integration`` does not apply.

    ``displacements``: a reference brought by the user (their own nonlinear FEM, measured
    displacements), one list per load case (spec order) of one ``[ux, uy, uz]`` per lattice
    node (node order of the built solid), m. When given it takes the FEM's place in the cost and
    in every reported figure, and no FEM is solved. Its shape is checked against the built solid
    in :func:`fpm.model.problem.load_problem` (errors at ``reference.displacements``); values
    must be finite.
    """

    integration: Integration = Field(
        "selective",
        description="hexahedra (linear and neo-Hookean): 'selective' (shear at 2x2x2 Gauss "
        "points, volume on the mean dilatation: B-bar, no volumetric locking) or 'full' (2x2x2 "
        "for all, the paper's)",
    )
    displacements: list[list[Vector3]] | None = Field(
        None,
        description="a supplied reference instead of the FEM: per load case, per lattice node, "
        "[ux, uy, uz], m (finite); null = solve the FEM",
    )
    mesh: ReferenceMesh | None = Field(
        None,
        description="the solid's tetrahedral mesh: the linear FEM is solved on it with 10-node "
        "tetrahedra and read at the lattice nodes (loads and fixed nodes mapped by position); "
        "null = the lattice's hexahedra",
        exclude_if=lambda v: v is None,
    )
    mesh_id: str | None = Field(
        None,
        pattern=MESH_ID_PATTERN,
        description="service only: the id of a mesh uploaded with POST /v1/meshes, used as "
        "'mesh' is",
        exclude_if=lambda v: v is None,
    )
    refine: Annotated[int, Field(ge=0, le=MAX_REFINE)] | Literal["auto", "check"] | None = Field(
        None,
        description="uniform refinements of the reference's mesh (each tetrahedron or "
        "hexahedron into 8), the lattice's forces spread over each node's share of the solid: "
        "n (the result's estimated error is the change from n - 1), 'auto' (refine until the "
        "displacements at the lattice nodes change by less than 1% or the next level is over "
        "node_budget), 'check' (the reference as given, its error estimated by one refinement) "
        "or 0 (as given, point loads, no estimate); null = 'auto' for a tetrahedral mesh, "
        "'check' for hexahedra (on lattices of at most about 7,500 nodes), 0 for a neo-Hookean "
        "or supplied reference",
        exclude_if=lambda v: v is None,
    )
    node_budget: int | None = Field(
        None,
        ge=1_000,
        le=20_000_000,
        description="refine: the most FEM nodes a refined level may have (null = 400,000)",
        exclude_if=lambda v: v is None,
    )

    @model_validator(mode="after")
    def _one_reference(self) -> ReferenceSettings:
        given = [
            name for name in ("displacements", "mesh", "mesh_id") if getattr(self, name) is not None
        ]
        if len(given) > 1:
            raise ValueError(f"give at most one of displacements, mesh, mesh_id (got {given})")
        return self

    @field_validator("refine", mode="before")
    @classmethod
    def _no_bool(cls, v: Any) -> Any:
        if isinstance(v, bool):  # JSON true is not a number of refinements
            raise ValueError("give a number of refinements (0-6), 'auto' or 'check'")
        return v


class ProblemSpec(_Strict):
    """A calibration (or simulation) problem."""

    name: str = "unnamed"
    material: Material | TransverselyIsotropicMaterial = Field(
        description="isotropic (default) or, with type 'transversely-isotropic', transversely "
        "isotropic"
    )
    geometry: Geometry
    fixed: list[Selector] = Field(description="fixed nodes; [] = none (FPM only)")
    load_cases: list[LoadCase] = Field(min_length=1)
    validation_cases: list[LoadCase] = Field(
        [],
        description="load cases the fit never sees (same form as load_cases): simulated at "
        "the fitted parameters and reported beside the fit (validation_relative_discrepancy): "
        "the honest measure of how the model does on loads it was not fitted to",
    )
    fpm: FpmSettings = Field(default_factory=FpmSettings)
    annealing: AnnealingSettings = Field(default_factory=AnnealingSettings)
    reference: ReferenceSettings = Field(default_factory=ReferenceSettings)

    @field_validator("material", mode="wrap")
    @classmethod
    def _material_type(cls, v: Any, handler: Any) -> Material | TransverselyIsotropicMaterial:
        return validate_material(v)

    @model_validator(mode="before")
    @classmethod
    def _default_stiffness(cls, data: Any) -> Any:
        """No fpm.stiffness: 'families+volume' where the lattice has cells with face diagonals
        (a box, voxels or mesh not of 'axis' connectivity), else 'single'."""
        if not isinstance(data, dict):
            return data
        settings = data.get("fpm")
        if isinstance(settings, dict) and "stiffness" in settings:
            return data
        if settings is not None and not isinstance(settings, dict):
            return data  # a FpmSettings instance, or the field's own error
        g = data.get("geometry")
        kind = g.get("type") if isinstance(g, dict) else getattr(g, "type", None)
        connectivity = (
            g.get("connectivity", "full") if isinstance(g, dict) else getattr(g, "connectivity", "")
        )
        has_cells = kind in ("box", "voxels", "mesh") and connectivity != "axis"
        mode = "families+volume" if has_cells else "single"
        return {**data, "fpm": {**(settings or {}), "stiffness": mode}}
