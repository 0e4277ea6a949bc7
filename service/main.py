"""Builds the FastAPI app: ``uvicorn service.main:app``.

See /docs (Swagger UI) or /redoc for the OpenAPI document (with the paper's material A spec as
the example body), served with no CDN; the manual (``make docs``) at /guide; Prometheus metrics
at /metrics.
"""

from __future__ import annotations

from fastapi import Depends, FastAPI

from . import deps, docs, errors, metrics, openapi, web
from .deps import redis_client, require_api_key
from .limits import BodySizeLimit
from .routers import calibrations, exports, fem_references, health, meshes, parameter_sets, views
from .settings import Settings, get_settings


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app: routers under /v1 (API-key protected when keys are set), problem+json errors,
    offline docs, metrics.

    ``settings`` (tests) replaces the settings for every route and the middleware.
    """
    app = FastAPI(
        title="FPM calibration service",
        version="1.0",
        description="Calibrates a force propagation model (Choi et al. 2004) against a "
        "finite element (FEM) reference of the same solid (the spec's reference: hexahedra "
        "on the lattice, or 10-node tetrahedra on a mesh of the solid's surface), on a pool "
        "of RQ workers.",
        docs_url=None,  # served by service.docs, without a CDN
        redoc_url=None,
        generate_unique_id_function=openapi.operation_id,
    )
    config = settings or get_settings()
    if settings is not None:
        app.dependency_overrides[deps.settings] = lambda: settings
    protected = [Depends(require_api_key)]
    documented = errors.problem_responses(401, 500, 503)  # the rest route by route
    for module in (calibrations, fem_references, meshes, parameter_sets, exports, views, health):
        app.include_router(module.router, dependencies=protected, responses=documented)
    web.install(app, documented)  # the web view at /, its assets, the profile plot's JSON
    errors.install(app)
    openapi.install(app)
    docs.install(app)
    app.add_middleware(
        BodySizeLimit,
        max_bytes=config.max_body_bytes,
        per_path={meshes.router.prefix: config.max_mesh_bytes},
    )
    metrics.install(app, lambda: redis_client(config.redis_url, config.redis_timeout))
    return app


app = create_app()
