"""The spec's foundations: versions of the numerics, shared types, the strict base model and
the Lame constants (SI units)."""

from __future__ import annotations

from typing import Literal, TypeVar, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
)

MODEL_VERSION = "2026.12.09"
"""Version of the numerics behind a result; bump it whenever a change alters fitted values.
It is part of a calibration's identity, so a resubmitted spec is not answered from results
that older numerics computed."""
FEM_VERSION = "2026.12.08"
"""Version of the FEM reference's numerics; bump it whenever a change alters FEM displacements.
It is part of a stored reference's identity (references are kept without expiry), so new
calibrations are never served a reference that older FEM numerics computed."""
EXPORT_VERSION = "2026.12.10"
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


_M = TypeVar("_M", bound=BaseModel)


def exactly_one(model: _M, fields: tuple[str, ...]) -> _M:
    """``model`` when exactly one of its ``fields`` is given (not None); else ValueError."""
    given = [n for n in fields if getattr(model, n) is not None]
    if len(given) != 1:
        raise ValueError(
            f"give exactly one of {', '.join(fields)} (got {', '.join(given) or 'none'})"
        )
    return model


MaterialModel = Literal["linear", "neo-hookean"]
StiffnessMode = Literal["families+volume", "single", "families", "field"]
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
