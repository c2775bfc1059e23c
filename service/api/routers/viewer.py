"""The web viewer: static files (plain ES modules, Leaflet vendored) at /viewer/, and / leading there.

The page talks only to the public API (/v1/...), with the caller's API key when one is set.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parent.parent / "viewer" / "static"  # service/api/viewer/static


def register_viewer(app: FastAPI) -> None:
    """Serve the viewer at /viewer/ (index.html) and redirect / to it."""

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/viewer/", status_code=307)

    app.mount("/viewer", StaticFiles(directory=STATIC_DIR, html=True), name="viewer")
