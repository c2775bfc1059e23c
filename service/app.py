"""FastAPI application factory: assembles routers, error handlers and the job runner."""

from __future__ import annotations

from fastapi import FastAPI

from service.settings import Settings, get_settings
from slam_engine import __version__


def create_app(settings: Settings | None = None) -> FastAPI:
    """A ready-to-serve app for ``settings`` (read from the environment when omitted)."""
    settings = settings or get_settings()
    app = FastAPI(title="lidarmap", version=__version__,
                  description="Occupancy grid, texture map and trajectory from drive logs, by "
                              "particle-filter SLAM.")
    app.state.settings = settings

    @app.get("/healthz", tags=["health"])
    def healthz() -> dict[str, str]:
        """Liveness: the process answers."""
        return {"status": "ok", "version": __version__}

    return app
