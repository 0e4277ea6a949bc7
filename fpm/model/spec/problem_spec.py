"""The whole spec: :class:`ProblemSpec`."""

from __future__ import annotations

from typing import Any

from pydantic import (
    Field,
    field_validator,
    model_validator,
)

from .base import _Strict
from .geometry import Geometry, LoadCase, Selector
from .materials import Material, TransverselyIsotropicMaterial, validate_material
from .reference import ReferenceSettings
from .settings import AnnealingSettings, FpmSettings


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
