"""/v1/sessions/{id}/logs: upload a drive log (validated on arrival) and list the uploads."""

from __future__ import annotations

from functools import partial
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from starlette.concurrency import run_in_threadpool

from api_schemas.error_body import ErrorResponse
from api_schemas.logs import LogPublic, LogsPublic
from service.api.convert import log_public
from service.api.deps import DataDep, SessionDep, SettingsDep, StoreDep
from service.http_errors import InvalidInput, NotFound
from service.storage.disk_space import ensure_free_space
from service.storage.inspection import LogInspector
from service.storage.store import new_id
from service.storage.uploads import UPLOAD_OPENAPI, extract_zip, is_zip_upload, move_into, receive_upload, safe_suffix

router = APIRouter(prefix="/v1/sessions/{session_id}/logs", tags=["logs"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse}})


def get_inspector(request: Request) -> LogInspector:
    return request.app.state.inspector


InspectorDep = Annotated[LogInspector, Depends(get_inspector)]


def known_format_names() -> list[str]:
    from slam_engine.formats import list_formats

    return [info.name for info in list_formats()]


@router.post("", response_model=LogPublic, status_code=201, openapi_extra=UPLOAD_OPENAPI,
             responses={400: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                        415: {"model": ErrorResponse}, 422: {"model": ErrorResponse}})
async def upload_log(request: Request, session: SessionDep, store: StoreDep, data: DataDep,
                     settings: SettingsDep, inspector: InspectorDep,
                     format: Annotated[str | None, Query(max_length=32, description="Format name; "
                                                         "default auto-detect.")] = None) -> LogPublic:
    """Upload a drive log in any supported format (a folder format as a .zip). The body is
    streamed to disk and hashed; the loader then checks it: 415 when no format matches, 422 with
    the loader's message when it is corrupt, 413 when too big."""
    received = await receive_upload(request, data.tmp, settings.max_upload_bytes,
                                    space=partial(ensure_free_space, data, settings.min_free_bytes))
    log_id = new_id()
    upload_dir = data.upload_dir(log_id)
    try:
        format_name = (format or received.fields.get("format") or "auto").strip()
        if format_name != "auto" and format_name not in known_format_names():
            raise InvalidInput(f"unknown format {format_name!r}; known: {', '.join(known_format_names())}",
                               {"field": "format"})
        archive = is_zip_upload(received) and not await inspector.is_log_file(received.path, format_name)
        if archive:
            log_path = await run_in_threadpool(extract_zip, received.path, upload_dir / "tree",
                                               settings.max_zip_entries, settings.max_extracted_bytes,
                                               partial(ensure_free_space, data, settings.min_free_bytes),
                                               settings.max_zip_ratio)
            received.path.unlink(missing_ok=True)
        else:
            log_path = upload_dir / f"log{safe_suffix(received.filename)}"
            move_into(received.path, log_path)
        summary = await inspector.summary(log_path, format_name, hidden_prefix=f"{upload_dir}/")
        row = store.add_log(log_id, session.id, received.filename, received.size_bytes, received.sha256,
                            archive, summary, data.relative(log_path))
        if row is None:
            raise NotFound("the session was deleted while the log was uploaded; nothing was stored",
                           {"session_id": session.id})
    except BaseException:  # nothing half-stored: no row without its files, no files without a row
        received.path.unlink(missing_ok=True)
        data.remove(upload_dir)
        raise
    return log_public(row)


@router.get("", response_model=LogsPublic)
def list_logs(session: SessionDep, store: StoreDep) -> LogsPublic:
    rows = store.list_logs(session.id)
    return LogsPublic(data=[log_public(r) for r in rows], count=len(rows))
