"""/v1/sessions/{id}/maps: upload a saved map (a map bundle) to localise in and extend."""

from __future__ import annotations

import os
from functools import partial

from fastapi import APIRouter, Request

from api_schemas.error_body import ErrorResponse
from api_schemas.jobs import JobPublic, JobSource, JobStatus
from service.api.convert import job_public
from service.api.deps import DataDep, SessionDep, SettingsDep, StoreDep
from service.api.routers.logs import InspectorDep
from service.http_errors import NotFound
from service.jobs.saved_maps import BUNDLE
from service.storage.disk_space import ensure_free_space
from service.storage.uploads import UPLOAD_OPENAPI, move_into, receive_upload

router = APIRouter(prefix="/v1/sessions/{session_id}/maps", tags=["maps"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse}})


@router.post("", response_model=JobPublic, status_code=201, openapi_extra=UPLOAD_OPENAPI,
             responses={400: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                        422: {"model": ErrorResponse}})
async def upload_map(request: Request, session: SessionDep, store: StoreDep, data: DataDep,
                     settings: SettingsDep, inspector: InspectorDep) -> JobPublic:
    """Upload a saved map: the ``map_bundle.npz`` a lidarmap run or job wrote (docs/map-bundle.md). It is
    checked in a bounded process (format version, array shapes and sizes; 422 with what is wrong, 413
    past the upload limit) and listed as a finished job of source 'map' whose product is the bundle:
    name its id as ``map_job_id`` to localise a drive in it or extend it."""
    received = await receive_upload(request, data.tmp, settings.max_upload_bytes,
                                    space=partial(ensure_free_space, data, settings.min_free_bytes))
    row = None
    try:
        summary = await inspector.bundle_summary(received.path, hidden_prefix=f"{data.tmp}/")
        row = store.create_job(session.id, session.owner, JobSource.MAP, None, {"mode": "map", "imported": True})
        move_into(received.path, data.job_dir(row.id) / "products" / BUNDLE)
        store.set_input(row.id, {"source": "map", "filename": received.filename, "sha256": received.sha256,
                                 "size_bytes": received.size_bytes, "summary": summary})
        store.set_products(row.id, {BUNDLE: f"products/{BUNDLE}"})
        store.mark_running(row.id, os.getpid())
        if not store.finish(row.id, JobStatus.SUCCEEDED):
            raise NotFound("the session was deleted while the map was uploaded; nothing was stored",
                           {"session_id": session.id})
    except BaseException:  # nothing half-stored
        received.path.unlink(missing_ok=True)
        if row is not None:
            data.remove(data.job_dir(row.id))
            store.finish(row.id, JobStatus.FAILED, "the map upload did not complete")
        raise
    done = store.get_job(row.id)
    assert done is not None
    return job_public(done)
