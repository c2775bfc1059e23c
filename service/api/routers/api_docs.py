"""The API documentation pages, /docs (Swagger UI) and /redoc (ReDoc), with their scripts and styles
served by the app itself from ``service/api/docs_assets`` (vendored, pinned; no CDN): they work with no
internet access. FastAPI's own pages are switched off (``docs_url=None, redoc_url=None``)."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from starlette.requests import Request

ASSETS_DIR = Path(__file__).resolve().parent.parent / "docs_assets"  # service/api/docs_assets
ASSETS_URL = "/static/docs"
SWAGGER_UI_VERSION = "5.35.0"  # docs_assets/PROVENANCE.md
REDOC_VERSION = "2.5.4"
# The pages may load nothing from elsewhere (ReDoc's sidebar would fetch its maker's logo from a CDN):
# their own inline start-up script and styles, the assets above, the schema, ReDoc's blob: worker.
CONTENT_SECURITY_POLICY = ("default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
                           "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'")


def _self_contained(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = CONTENT_SECURITY_POLICY
    return page


def register_api_docs(app: FastAPI) -> None:
    """/docs, its OAuth2 redirect page, /redoc, and the assets under ``ASSETS_URL``."""
    app.mount(ASSETS_URL, StaticFiles(directory=ASSETS_DIR), name="api-docs-assets")
    openapi_url = app.openapi_url or "/openapi.json"
    oauth2_redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"
    favicon = f"{ASSETS_URL}/swagger-ui/favicon-32x32.png"

    # plain routes, as FastAPI adds its own pages (and /openapi.json): open, outside the API's routes and schema
    async def swagger_ui(request: Request) -> HTMLResponse:
        return _self_contained(get_swagger_ui_html(
            openapi_url=openapi_url, title=f"{app.title} - Swagger UI", oauth2_redirect_url=oauth2_redirect_url,
            swagger_js_url=f"{ASSETS_URL}/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS_URL}/swagger-ui/swagger-ui.css", swagger_favicon_url=favicon,
            swagger_ui_parameters={"validatorUrl": None}))  # no badge fetched from the validator's site

    async def swagger_ui_redirect(request: Request) -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    async def redoc(request: Request) -> HTMLResponse:
        return _self_contained(get_redoc_html(
            openapi_url=openapi_url, title=f"{app.title} - ReDoc",
            redoc_js_url=f"{ASSETS_URL}/redoc/redoc.standalone.js", redoc_favicon_url=favicon, with_google_fonts=False))

    app.add_route("/docs", swagger_ui, include_in_schema=False)
    app.add_route(oauth2_redirect_url, swagger_ui_redirect, include_in_schema=False)
    app.add_route("/redoc", redoc, include_in_schema=False)
