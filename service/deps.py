"""FastAPI dependencies: settings, the Redis client, the API-key check, ids in paths.

Each is ``async def`` although none awaits: they only compute, and FastAPI runs a plain
``def`` dependency on its thread pool, one hop per dependency per request (five on a status
poll), which under CPU contention adds to every request's latency. The routes that block on
Redis stay plain functions, on the pool."""

from __future__ import annotations

import hmac
import re
from functools import lru_cache
from typing import Annotated

from fastapi import Depends, Path, Security
from fastapi.security import APIKeyHeader
from redis import Redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from store import keys, quotas

from .errors import ProblemError
from .settings import Settings, get_settings


async def settings() -> Settings:
    """The service's settings (:func:`get_settings`; tests override this dependency)."""
    return get_settings()


SettingsDep = Annotated[Settings, Depends(settings)]


@lru_cache(maxsize=8)
def redis_client(url: str, timeout: float) -> Redis:
    """One pooled client per (url, timeout).

    Socket timeouts and a single immediate retry: an unreachable Redis fails a request within
    about ``2 * timeout`` seconds (answered 503), never hangs it.
    """
    return Redis.from_url(
        url,
        socket_timeout=timeout,
        socket_connect_timeout=timeout,
        retry=Retry(NoBackoff(), 1),
        health_check_interval=30,
    )


async def get_redis(settings: SettingsDep) -> Redis:
    return redis_client(settings.redis_url, settings.redis_timeout)


RedisDep = Annotated[Redis, Depends(get_redis)]

api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


async def require_api_key(
    settings: SettingsDep, key: Annotated[str | None, Security(api_key_header)]
) -> None:
    """When API keys are configured, every /v1 route needs one of them in X-API-Key.

    Compared in constant time; the key is never logged or echoed.
    """
    if not settings.api_keys:
        return
    given = (key or "").encode()
    if not any(
        hmac.compare_digest(given, k.get_secret_value().encode()) for k in settings.api_keys
    ):
        raise ProblemError(
            401,
            "Unauthorized",
            "missing or unknown API key (send it in the X-API-Key header)",
            headers={"WWW-Authenticate": "X-API-Key"},
        )


async def owner(settings: SettingsDep, key: Annotated[str | None, Security(api_key_header)]) -> str:
    """Who a request counts against for the per-key quotas: a hash of its API key (never the
    key), or "anonymous" when the service has no keys."""
    return quotas.owner_of(key if settings.api_keys else None)


OwnerDep = Annotated[str, Depends(owner)]


def _known_form(value: str, pattern: re.Pattern[str], what: str) -> str:
    """``value`` if it has the form of ``what``'s ids, else 404 like an unknown id.

    Ids go into Redis keys: ``<id>:progress`` would name another key of that calibration (of
    another type: a 500), so no id reaches a key unchecked.
    """
    if pattern.fullmatch(value) is None:
        raise ProblemError(404, "Not found", f"no {what} {value!r}")
    return value


async def calibration_id(
    calibration_id: Annotated[str, Path(description="16 lowercase hex digits")],
) -> str:
    """The path's calibration id, checked against :data:`store.keys.CALIBRATION_ID`."""
    return _known_form(calibration_id, keys.CALIBRATION_ID, "calibration")


async def fem_id(
    fem_id: Annotated[str, Path(description="64 lowercase hex digits (sha256)")],
) -> str:
    """The path's FEM reference id, checked against :data:`store.keys.FEM_ID`."""
    return _known_form(fem_id, keys.FEM_ID, "FEM reference")


async def parameter_set_id(
    parameter_set_id: Annotated[str, Path(description="'ps-' and 16 lowercase hex digits")],
) -> str:
    """The path's parameter set id, checked against :data:`store.keys.PARAMETER_SET_ID`."""
    return _known_form(parameter_set_id, keys.PARAMETER_SET_ID, "parameter set")


# Route parameters of these types are checked before the route runs (404 otherwise).
CalibrationId = Annotated[str, Depends(calibration_id)]
FemId = Annotated[str, Depends(fem_id)]
ParameterSetId = Annotated[str, Depends(parameter_set_id)]
