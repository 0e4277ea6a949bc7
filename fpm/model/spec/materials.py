"""``material``: isotropic (with regions of other materials) or transversely isotropic
(moduli in Pa, densities in kg/m^3)."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import (
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from .base import MaterialModel, Vector3, _Strict, exactly_one


class Material(_Strict):
    """Isotropic elastic constants (paper Table 1) and the FEM reference's material model.

    ``model``: ``"linear"`` (small-strain linear elasticity, the paper's, default) or
    ``"neo-hookean"`` (compressible neo-Hookean, large deformation: :mod:`fpm.fem.hyperelastic`),
    both from the same E and nu. ``"linear"`` is left out of dumps, so a linear spec's
    identity (content hash) does not depend on the field.
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
        return exactly_one(self, REGION_SELECTOR_FIELDS)


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
