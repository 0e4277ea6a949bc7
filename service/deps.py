"""FastAPI dependencies: settings, the Redis client, the API-key check."""

from __future__ import annotations

import hmac
from functools import lru_cache
from typing import Annotated

from fastapi import Depends, Security
from fastapi.security import APIKeyHeader
from redis import Redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from .errors import ProblemError
from .settings import Settings, get_settings

SettingsDep = Annotated[Settings, Depends(get_settings)]


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


def get_redis(settings: SettingsDep) -> Redis:
    return redis_client(settings.redis_url, settings.redis_timeout)


RedisDep = Annotated[Redis, Depends(get_redis)]

api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


def require_api_key(
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
