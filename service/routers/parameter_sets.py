"""/v1/parameter-sets: stored (k, d, depth) sets, filtered by material constants."""

from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import APIRouter, Query
from redis import Redis

from store import records

from ..deps import ParameterSetId, RedisDep
from ..errors import ProblemError, problem_responses
from ..schemas import ParameterSet, ParameterSetPage

router = APIRouter(prefix="/v1/parameter-sets", tags=["parameter-sets"])

RELATIVE_TOLERANCE = 1e-6
"""Material constants match when equal to this relative tolerance."""


def current(ps: dict[str, Any]) -> bool:
    """False for a set stored by an older version (no relative discrepancy, no family
    stiffnesses): the listing leaves it out and reading it answers 410."""
    return "relative_discrepancy" in ps and "stiffness" in ps


def stored_parameter_set(redis: Redis, parameter_set_id: str) -> dict[str, Any]:
    """The stored parameter set; 404 if there is none, 410 if an older version stored it."""
    ps = records.get_parameter_set(redis, parameter_set_id)
    if ps is None:
        raise ProblemError(404, "Not found", f"no parameter set {parameter_set_id!r}")
    if not current(ps):
        raise ProblemError(
            410,
            "Gone",
            f"parameter set {parameter_set_id} was stored by an older version of the service "
            "(no relative discrepancy): calibrate its spec again",
        )
    return ps


@router.get("", operation_id="list_parameter_sets", responses=problem_responses(422))
def listing(
    redis: RedisDep,
    youngs_modulus: Annotated[float | None, Query(gt=0, description="E, Pa")] = None,
    poisson_ratio: Annotated[float | None, Query(gt=-1, lt=0.5)] = None,
    density: Annotated[float | None, Query(gt=0, description="kg/m^3")] = None,
    connectivity: Annotated[str | None, Query(description="axis | axis+face | full")] = None,
    name: Annotated[str | None, Query(description="substring of the spec name")] = None,
) -> ParameterSetPage:
    """Stored parameter sets, newest first, filtered by material constants (and more).

    Sets stored by older versions of the service (before relative discrepancies) are left out.
    """
    wanted = {"youngs_modulus": youngs_modulus, "poisson_ratio": poisson_ratio, "density": density}

    def matches(ps: dict[str, Any]) -> bool:
        for key, value in wanted.items():
            if value is not None and not (
                ps["material"].get(key) is not None  # a transversely isotropic set has no E
                and math.isclose(ps["material"][key], value, rel_tol=RELATIVE_TOLERANCE)
            ):
                return False
        if connectivity is not None and ps["geometry"].get("connectivity") != connectivity:
            return False
        return name is None or name.lower() in ps["name"].lower()

    stored = records.list_parameter_sets(redis)
    items = [ParameterSet(**ps) for ps in stored if current(ps) and matches(ps)]
    return ParameterSetPage(items=items, total=len(items))


@router.get(
    "/{parameter_set_id}",
    operation_id="get_parameter_set",
    responses=problem_responses(404, 410),
)
def read(parameter_set_id: ParameterSetId, redis: RedisDep) -> ParameterSet:
    """One stored parameter set (410 for one stored by an older version: recalibrate)."""
    return ParameterSet(**stored_parameter_set(redis, parameter_set_id))
