"""/v1/sessions: create, list, read, delete."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Query

from api_schemas.error_body import ErrorResponse
from api_schemas.sessions import SessionCreate, SessionDeleted, SessionPublic, SessionsPublic
from service.api.convert import session_public
from service.api.deps import MAX_OFFSET, DataDep, OwnerDep, RunnerDep, SessionDep, SettingsDep, StoreDep
from service.storage.data_dir import DataDir

STOP_MARGIN_S = 3.0  # after the cancel grace, the runner's time to stop the worker and record it

router = APIRouter(prefix="/v1/sessions", tags=["sessions"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                              422: {"model": ErrorResponse}})


@router.post("", response_model=SessionPublic, status_code=201)
def create_session(body: SessionCreate, store: StoreDep, owner: OwnerDep) -> SessionPublic:
    """Start a session; streamed chunks need its calibration (or preset), uploads carry their own."""
    row = store.create_session(owner, body.name, body.vehicle_preset,
                               None if body.calibration is None else body.calibration.model_dump(),
                               None if body.geo is None else body.geo.model_dump())
    return session_public(row)


@router.get("", response_model=SessionsPublic)
def list_sessions(store: StoreDep, owner: OwnerDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100,
                  offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> SessionsPublic:
    rows, count = store.list_sessions(owner, limit, offset)
    return SessionsPublic(data=[session_public(r) for r in rows], count=count)


@router.get("/{session_id}", response_model=SessionPublic)
@router.head("/{session_id}", response_model=SessionPublic, name="get_session (head)")
def get_session(session: SessionDep) -> SessionPublic:
    """The session (HEAD: its headers only)."""
    return session_public(session)


@router.delete("/{session_id}", response_model=SessionDeleted)
def delete_session(session: SessionDep, store: StoreDep, runner: RunnerDep, data: DataDep,
                   settings: SettingsDep) -> SessionDeleted:
    """Cancel the session's active jobs and wait until they stopped (their worker is stopped after the
    cancel grace period), then delete the session with its logs, chunks, jobs and files."""
    jobs, _ = store.list_jobs(session.owner, session.id, None, 1_000_000, 0)
    active = [job.id for job in jobs if job.active]
    # the files of what no job still reads go first: on a full disk the database's own writes below
    # (the cancel, the delete) need room, and deleting a session is how a user makes room (it answered
    # 507 there and freed nothing)
    _remove_files(data, session.id, [] if active else [log.id for log in store.list_logs(session.id)],
                  [job.id for job in jobs if not job.active], chunks=not active)
    for job_id in active:
        store.request_cancel(job_id)
        runner.cancel(job_id)
    wait_until_stopped(store, active, settings.cancel_grace_s + STOP_MARGIN_S)
    log_ids = [log.id for log in store.list_logs(session.id)]
    _remove_files(data, session.id, log_ids, store.delete_session(session.id), chunks=True)
    return SessionDeleted(id=session.id, jobs_cancelled=len(active))


def _remove_files(data: DataDir, session_id: str, log_ids: list[str], job_ids: list[str], chunks: bool) -> None:
    """Remove the uploads of ``log_ids``, the folders of ``job_ids`` and, with ``chunks``, the session's chunks."""
    for log_id in log_ids:
        data.remove(data.upload_dir(log_id))
    for job_id in job_ids:
        data.remove(data.job_dir(job_id))
    if chunks:
        data.remove(data.chunk_dir(session_id))


def wait_until_stopped(store: StoreDep, job_ids: list[str], timeout_s: float) -> None:
    """Poll until none of ``job_ids`` is queued or running (so none writes files any more), or timeout."""
    deadline = time.monotonic() + timeout_s
    while job_ids and time.monotonic() < deadline:
        rows = [store.get_job(j) for j in job_ids]
        job_ids = [row.id for row in rows if row is not None and row.active]
        if job_ids:
            time.sleep(0.05)
