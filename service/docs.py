"""The API's documentation pages, offline: Swagger UI at ``/docs`` and ReDoc at ``/redoc``.

FastAPI's own pages load their scripts, style sheet and favicon from a CDN (and ReDoc its
fonts from Google), so on a machine without internet they stay blank. Here the assets come from
the installed ``fastapi-offline`` package (Swagger UI 5 and ReDoc 2 bundles), served by the app
under :data:`ASSETS`; the pages name no other host (Swagger UI's online validator is off).

Beside them, the manual at ``/guide``: the site ``make docs`` builds (mkdocs, into ``site/`` at
the repository's root, or ``FPM_GUIDE_DIR``), served as static files. Where it is not built,
``/guide`` answers 503 with a page that says to run ``make docs``. The directory is looked at on
each request, so a site built while the service runs is served at once.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send

ASSETS = "/docs-assets"
"""Where the bundles are served: swagger-ui-bundle.js, swagger-ui.css, redoc.standalone.js,
favicon.png."""

FILES = Path(fastapi_offline.__file__).resolve().parent / "static"

GUIDE = "/guide"
"""Where the manual is served."""

SITE = Path(__file__).resolve().parents[1] / "site"
"""Where ``make docs`` builds the manual (``FPM_GUIDE_DIR`` overrides it)."""


def guide_dir() -> Path:
    return Path(os.environ.get("FPM_GUIDE_DIR") or SITE)


class Guide:
    """The built manual as static files (``index.html`` for a directory), or a 503 page saying
    how to build it."""

    def __init__(self, directory: Path | None = None):
        self.directory = directory
        self.files: StaticFiles | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        site = self.directory or guide_dir()
        if not (site / "index.html").is_file():
            page = (
                "<!doctype html><title>Manual not built</title>"
                "<h1>The manual is not built</h1>"
                f"<p>No built manual in <code>{html.escape(str(site))}</code>. Run "
                "<code>make docs</code> in the project's directory (it writes "
                "<code>site/</code>), then reload this page.</p>"
                "<p>The API's own documentation is at <code>/docs</code>.</p>"
            )
            await HTMLResponse(page, status_code=503)(scope, receive, send)
            return
        if self.files is None or Path(str(self.files.directory)) != site:
            self.files = StaticFiles(directory=site, html=True)
        await self.files(scope, receive, send)


def install(app: FastAPI, docs_url: str = "/docs", redoc_url: str = "/redoc") -> None:
    """Serve the two pages and their assets (create ``app`` with ``docs_url=None,
    redoc_url=None`` so that FastAPI's CDN pages are not registered first)."""
    app.mount(ASSETS, StaticFiles(directory=FILES), name="docs-assets")
    app.mount(GUIDE, Guide(), name="guide")
    oauth2_redirect = app.swagger_ui_oauth2_redirect_url

    def root(request: Request) -> str:
        return str(request.scope.get("root_path", "")).rstrip("/")

    @app.get(docs_url, include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        base = root(request)
        return get_swagger_ui_html(
            openapi_url=f"{base}{app.openapi_url}",
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=f"{base}{oauth2_redirect}" if oauth2_redirect else None,
            swagger_js_url=f"{base}{ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{base}{ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{base}{ASSETS}/favicon.png",
            swagger_ui_parameters={"validatorUrl": None, **(app.swagger_ui_parameters or {})},
        )

    if oauth2_redirect:

        @app.get(oauth2_redirect, include_in_schema=False)
        def swagger_ui_redirect() -> HTMLResponse:
            return get_swagger_ui_oauth2_redirect_html()

    @app.get(redoc_url, include_in_schema=False)
    def redoc(request: Request) -> HTMLResponse:
        base = root(request)
        return get_redoc_html(
            openapi_url=f"{base}{app.openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{base}{ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{base}{ASSETS}/favicon.png",
            with_google_fonts=False,
        )
