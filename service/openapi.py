"""The OpenAPI document, shaped for client generators (openapi-python-client and the like).

- Every error response refers to one ``Problem`` component (:class:`service.errors.Problem`),
  application/problem+json: a generator makes one model of it and types every error answer.
- FastAPI's own 422 (``HTTPValidationError``, application/json) is never what the service
  answers (its handler answers problem+json), so wherever FastAPI adds it, it becomes the
  Problem response, and the unused ``HTTPValidationError`` / ``ValidationError`` components go.
- A one-value ``const`` (what pydantic writes for ``Literal["auto"]``) becomes the equivalent
  one-value ``enum``: openapi-python-client 0.29 parses ``int | const`` wrongly (the spec's
  ``fpm.depth: 3`` raised "must match const 'auto'") and handles ``int | enum`` well.
- Operation ids are readable (``submit_calibration``, ``list_parameter_sets``): routes set them
  explicitly, and :func:`operation_id` names any route that does not.
"""

from __future__ import annotations

import json
import re
from typing import Any

from fastapi import FastAPI
from fastapi.routing import APIRoute

from .errors import MEDIA_TYPE, PROBLEM_DESCRIPTIONS, PROBLEM_REF, Problem

COMPONENTS = "#/components/schemas/"
FASTAPI_422 = COMPONENTS + "HTTPValidationError"


def operation_id(route: APIRoute) -> str:
    """The operation id of a route that sets none: its function's name and its first tag,
    snake_case (``read`` under ``fem-references`` -> ``read_fem_references``), instead of
    FastAPI's ``read_v1_fem_references__fem_id__get``."""
    words = [route.name, *(route.tags[:1])]
    return re.sub(r"[^0-9a-zA-Z]+", "_", "_".join(str(w) for w in words)).strip("_").lower()


def _problem_components() -> dict[str, Any]:
    """The Problem schema and the schemas it refers to, as component entries."""
    schema = Problem.model_json_schema(ref_template=COMPONENTS + "{model}")
    defs = schema.pop("$defs", {})
    return {**defs, "Problem": schema}


def _const_to_enum(node: Any) -> None:
    """Every ``{"const": x}`` under ``node`` as ``{"enum": [x]}`` (in place)."""
    if isinstance(node, dict):
        if "const" in node and "enum" not in node:
            node["enum"] = [node.pop("const")]
        for value in node.values():
            _const_to_enum(value)
    elif isinstance(node, list):
        for value in node:
            _const_to_enum(value)


def shape(document: dict[str, Any]) -> dict[str, Any]:
    """Put the Problem component in ``document``, point FastAPI's 422s at it, and write
    consts as enums (in place)."""
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    schemas.update(_problem_components())
    for operations in document.get("paths", {}).values():
        for operation in operations.values():
            responses = operation.get("responses", {})
            default = responses.get("422", {}).get("content", {}).get("application/json", {})
            if default.get("schema", {}).get("$ref") == FASTAPI_422:
                responses["422"] = {
                    "description": PROBLEM_DESCRIPTIONS[422],
                    "content": {MEDIA_TYPE: {"schema": PROBLEM_REF}},
                }
    for name in ("HTTPValidationError", "ValidationError"):
        schema = schemas.pop(name, None)
        if schema is not None and f'"{COMPONENTS}{name}"' in json.dumps(document):
            schemas[name] = schema  # still referred to (by something of ours): keep it
    _const_to_enum(schemas)
    return document


def install(app: FastAPI) -> None:
    """Have ``app`` serve the shaped document (built once, on the first request)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = shape(build())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
