"""Errors as RFC 9457 problem details (``application/problem+json``).

Every error the service returns goes through here: our own :class:`ProblemError`, FastAPI's
request validation (422 naming the field), spec checks from :func:`fpm.load_problem`
(422), an unreachable Redis (503), unknown routes (404/405) and anything unexpected (500,
with no traceback in the answer).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field, ValidationError
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from store.text import escape

MEDIA_TYPE = "application/problem+json"
log = logging.getLogger("service")


class FieldError(BaseModel):
    """One bad field of a 422: its dotted location and why."""

    field: str = Field(description="dotted location, e.g. load_cases.0.forces.0.at")
    message: str


class Problem(BaseModel):
    """RFC 9457 problem details: every error answer of the service (application/problem+json)."""

    type: str = Field("about:blank", description="'about:blank': the status says it all")
    title: str = Field(description="short summary of the status, e.g. 'Invalid input'")
    status: int = Field(description="the HTTP status code")
    detail: str = Field(description="what went wrong, for a person (a 422 lists every field)")
    errors: list[FieldError] | None = Field(
        None, description="422 only: each bad field (dotted location) and why"
    )


PROBLEM_REF = {"$ref": "#/components/schemas/Problem"}
"""The one schema every error response refers to (:func:`service.openapi.install` puts
:class:`Problem` into the document's components)."""

PROBLEM_DESCRIPTIONS = {
    400: "the body cannot be read (e.g. not UTF-8)",
    401: "missing or unknown API key",
    404: "no such resource",
    409: "the calibration has already finished",
    410: "stored by an older version of the service in a form it no longer serves",
    413: "request body over the configured limit",
    422: "invalid input: names each bad field and the reason",
    429: "over the API key's quota (calibrations or nodes in flight); Retry-After says when to "
    "try again",
    500: "an unexpected error (logged; no traceback in the answer)",
    503: "Redis (queue and store) unreachable; retry later",
}


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` documenting these error statuses as application/problem+json.

    Each refers to the one :class:`Problem` component (no inline copies: client generators
    make one model of it). A documented 422 also replaces FastAPI's default (a JSON body of
    another shape).
    """
    return {
        code: {
            "description": PROBLEM_DESCRIPTIONS[code],
            "content": {MEDIA_TYPE: {"schema": PROBLEM_REF}},
        }
        for code in codes
    }


class ProblemError(Exception):
    """An error answered as problem+json: status, short title, human detail, extra members."""

    def __init__(
        self,
        status: int,
        title: str,
        detail: str,
        *,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ):
        super().__init__(detail)
        self.status = status
        self.title = title
        self.detail = detail
        self.headers = headers
        self.extra = extra


def problem(
    status: int, title: str, detail: str, headers: dict[str, str] | None = None, **extra: Any
) -> JSONResponse:
    """A problem+json response."""
    body = {"type": "about:blank", "title": title, "status": status, "detail": detail, **extra}
    return JSONResponse(body, status_code=status, media_type=MEDIA_TYPE, headers=headers)


def field_errors(errors: Sequence[Any], strip: tuple[str, ...] = ()) -> list[dict[str, str]]:
    """[{field, message}] from pydantic errors; ``field`` is the dotted location.

    Location parts can be the client's own keys (an unknown field), and messages may quote
    input, so both are escaped: a lone surrogate would make the answer unencodable (a 500).
    A body that is not JSON at all is the ``body``'s error, its message the parser's with the
    character it stopped at (FastAPI locates it at ("body", offset): the offset is no field).
    """
    out = []
    for e in errors:
        if e.get("type") == "json_invalid":
            at = e["loc"][-1] if isinstance(e["loc"][-1], int) else None
            why = (e.get("ctx") or {}).get("error") or e["msg"]
            where = f" at character {at}" if at is not None else ""
            message = f"the body is not valid JSON ({why}{where})"
            out.append({"field": "body", "message": escape(message)})
            continue
        loc = [escape(str(p)) for p in e["loc"]]
        if loc and loc[0] in strip:
            loc = loc[1:]
        out.append({"field": ".".join(loc) or "body", "message": escape(e["msg"])})
    return out


def unprocessable(errors: list[dict[str, str]]) -> JSONResponse:
    """422 naming every bad field; ``detail`` repeats them as one readable line."""
    detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
    return problem(422, "Invalid input", detail, errors=errors)


def install(app: FastAPI) -> None:
    """Register the handlers on ``app``."""

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, exc.headers, **exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _request(request: Request, exc: RequestValidationError) -> JSONResponse:
        return unprocessable(field_errors(exc.errors(), strip=("body", "query", "path")))

    @app.exception_handler(ValidationError)
    async def _spec(request: Request, exc: ValidationError) -> JSONResponse:
        return unprocessable(field_errors(exc.errors()))

    @app.exception_handler(RedisConnectionError)
    @app.exception_handler(RedisTimeoutError)
    async def _redis(request: Request, exc: Exception) -> JSONResponse:
        log.warning("Redis unavailable: %s", type(exc).__name__)
        return problem(
            503,
            "Service unavailable",
            "the queue and store (Redis) cannot be reached; try again later",
            {"Retry-After": "5"},
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        title = {400: "Bad request", 404: "Not found", 405: "Method not allowed"}.get(
            exc.status_code, "Error"
        )
        return problem(exc.status_code, title, str(exc.detail), dict(exc.headers or {}))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %r", request.method, request.url.path)
        return problem(500, "Internal server error", "an unexpected error; it has been logged")
