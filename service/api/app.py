"""FastAPI application factory: assembles routers, error handlers, the store and the job runner."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from api_schemas.jobs import JobStatus
from service.api.access import KeyGateMiddleware
from service.api.error_handlers import install_error_handlers
from service.api.limits import BodyLimitMiddleware
from service.api.methods import AllowedMethodsMiddleware
from service.api.openapi_errors import document_errors
from service.api.routers import api_docs, chunks, formats, health, jobs, logs, maps, products, sessions
from service.api.routers.tile_schemes import router as tile_schemes_router
from service.api.routers.viewer import register_viewer
from service.jobs.events import job_event
from service.runners.factory import create_runner
from service.settings import Settings, get_settings
from service.storage.data_dir import DataDir
from service.storage.inspection import InspectionLimits, LogInspector
from service.storage.store import open_store
from service.storage.uploads import MULTIPART_OVERHEAD_BYTES
from slam_engine import __version__

logger = logging.getLogger("lidarmap.service")


def create_app(settings: Settings | None = None, job_function: str | None = None) -> FastAPI:
    """A ready-to-serve app for ``settings`` (read from the environment when omitted).

    ``job_function`` ("module:function") replaces the mapping job, for tests of the job lifecycle.
    The store, the data folder and the worker processes start with the app's lifespan.
    """
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        data = DataDir(settings.data_dir)
        data.create()
        data.remove_stale_temp_files()
        store = open_store(settings.database_url, data.database)
        store.initialise()
        # files nothing refers to (a crash mid-delete); uploads of another API host may be in flight
        # under uploads/ before their row exists, so those are swept only when this host is the only one
        orphans = data.remove_orphans(store.stored_ids(), uploads_and_chunks=settings.runner == "local")
        if orphans:
            logger.warning("removed %d folder(s) of deleted sessions, logs or jobs", orphans)
        if settings.runner == "local":  # Celery workers outlive the API: their jobs go on (the reaper watches them)
            interrupted = store.fail_interrupted()
            for job_id in interrupted:
                job_event(JobStatus.FAILED.value, job_id, logging.WARNING,
                          error="interrupted: the service stopped while the job was running")
        runner = create_runner(settings, data, store, job_function)
        for job_id in store.jobs_with_status(JobStatus.QUEUED):
            runner.submit(job_id)
        app.state.data, app.state.store, app.state.runner = data, store, runner
        app.state.inspector = LogInspector(InspectionLimits(
            settings.inspection_memory_limit_mb, settings.inspection_timeout_s, settings.max_extracted_bytes,
            settings.inspection_processes, settings.inspection_express_bytes, settings.inspection_express_timeout_s))
        try:
            yield
        finally:
            runner.shutdown()
            app.state.inspector.shutdown()
            store.close()

    app = FastAPI(title="lidarmap", version=__version__, lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Occupancy grid, texture map and trajectory from drive logs, by "
                              "particle-filter SLAM. Upload a log (or stream chunks) into a session, "
                              "start a job, poll it, fetch the products.")
    app.state.settings = settings
    install_error_handlers(app)

    def body_limit(path: str) -> int:
        if path.endswith("/logs"):
            return settings.max_upload_bytes + MULTIPART_OVERHEAD_BYTES
        return settings.max_chunk_bytes

    app.add_middleware(BodyLimitMiddleware, limit_for=body_limit, stall_timeout_s=settings.body_stall_timeout_s)
    app.add_middleware(AllowedMethodsMiddleware, openapi=lambda: app.openapi())  # the documented schema, at first use
    app.add_middleware(KeyGateMiddleware, keys=settings.api_key_list(), open_paths=settings.open_path_list())
    app.include_router(health.router)
    for module in (sessions, logs, maps, chunks, formats, products):
        app.include_router(module.router)
    app.include_router(jobs.session_jobs)
    app.include_router(jobs.router)
    app.include_router(tile_schemes_router)
    register_viewer(app)
    api_docs.register_api_docs(app)  # /docs and /redoc from the package's own assets
    document_errors(app)
    return app
