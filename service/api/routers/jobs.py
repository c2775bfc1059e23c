"""Jobs: create (on a session), list, read, cancel."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query

from api_schemas.error_body import ErrorResponse
from api_schemas.jobs import JobPublic, JobSource, JobsPublic, JobStatus
from service.api.convert import job_public
from service.api.deps import MAX_OFFSET, DataDep, JobDep, OwnerDep, RunnerDep, SessionDep, SettingsDep, StoreDep
from service.http_errors import Conflict, InvalidInput, NotFound
from service.jobs.estimate import check_job_memory, estimate_bytes
from service.jobs.products import engine_compiling, live_product_names
from service.jobs.saved_maps import saved_map_path
from service.jobs.settings import JobSettings, resolve, stored_config
from service.runners.base import JobRunner
from service.storage.rows import SessionRow
from service.storage.store import JobStore
from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError

ERRORS: dict[int | str, dict[str, Any]] = {401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                                           422: {"model": ErrorResponse}}

session_jobs = APIRouter(prefix="/v1/sessions/{session_id}/jobs", tags=["jobs"], responses=ERRORS)
router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=ERRORS)


@session_jobs.post("", response_model=JobPublic, status_code=202, responses={409: {"model": ErrorResponse}})
def create_job(body: JobSettings, session: SessionDep, store: StoreDep, runner: RunnerDep,
               settings: SettingsDep, data: DataDep) -> JobPublic:
    """Queue a mapping run over the session's newest (or the given) upload, or over its streamed
    chunks 0..k as they stand when the job starts. With ``live: true`` the job follows the stream
    instead, mapping chunks as they arrive until the stream is finished or idle (one live job per
    session; the session may have no chunks yet). Poll GET /v1/jobs/{id}. 422 when the parameters
    clearly need more memory than the job memory limit (the estimate in the detail)."""
    slam = resolve(body)  # the engine's bounds: 422 naming the setting
    config = stored_config(body, slam)
    scans = None  # known up front for an upload; a streamed job checks again once its input is read
    if not body.live and (body.source or (JobSource.LOG if session.logs else JobSource.STREAM)) is JobSource.LOG:
        logs = [store.get_log(body.log_id, session.id)] if body.log_id else list(store.list_logs(session.id))
        scans = logs[0].summary.get("streams", {}).get("scans") if logs and logs[0] else None
    refuse_costly_job(slam, scans, settings.job_memory_limit())
    if body.map_job_id is not None:
        saved_map_path(store, data, session.owner, body.map_job_id)  # 404 / 409 now, not when the job runs
    if body.live:
        return _create_live_job(config, session, store, runner)
    source = body.source or (JobSource.LOG if session.logs else JobSource.STREAM)
    log_id = None
    if source is JobSource.LOG:
        if body.log_id is not None:
            if store.get_log(body.log_id, session.id) is None:
                raise NotFound(f"no log {body.log_id!r} in this session", {"field": "log_id"})
            log_id = body.log_id
        elif newest := store.list_logs(session.id):
            log_id = newest[0].id
        else:
            raise Conflict("the session has no uploaded log: POST one to /v1/sessions/{id}/logs first",
                           {"session_id": session.id})
    else:
        if not session.chunks:
            raise Conflict("the session has no streamed chunks: POST some to /v1/sessions/{id}/chunks first "
                           "(or start a live job, which waits for them)", {"session_id": session.id})
        _check_stream_calibration(session)
    row = store.create_job(session.id, session.owner, source, log_id, config)
    runner.submit(row.id)
    return job_public(row)


def refuse_costly_job(config: SlamConfig, scans: int | None, limit_mb: int) -> None:
    """422 with the estimate when ``config`` clearly needs more than ``limit_mb``."""
    try:
        check_job_memory(config, scans, limit_mb)
    except ConfigError as exc:
        err = InvalidInput(str(exc), {"limit_mb": limit_mb, **estimate_bytes(config, scans)})
        err.code = "job_too_large"
        raise err from None


def _create_live_job(config: dict[str, Any], session: SessionRow, store: JobStore, runner: JobRunner) -> JobPublic:
    calibration = _check_stream_calibration(session)
    if calibration.get("lidar") is None:
        raise Conflict("a live job maps LiDAR scans as they arrive: the session's calibration needs 'lidar'",
                       {"session_id": session.id})
    row, active = store.create_live_job(session.id, session.owner, config)
    if row is None:
        assert active is not None  # no new row: because of this active live job
        raise Conflict(f"the session already has a live job ({active.id}, {active.status}): one live job per "
                       "session; cancel it or finish the stream first", {"job_id": active.id})
    runner.submit(row.id)
    return job_public(row)


def _check_stream_calibration(session: SessionRow) -> dict[str, Any]:
    """The session's calibration, which streamed chunks need (409 without one)."""
    if session.calibration is None:
        raise Conflict("streamed chunks need the vehicle's calibration: create the session with "
                       "'calibration'", {"session_id": session.id})
    return session.calibration


@router.get("", response_model=JobsPublic)
def list_jobs(store: StoreDep, owner: OwnerDep, data: DataDep,
              session: Annotated[str | None, Query(max_length=64, description="Only this session's jobs.")] = None,
              status: Annotated[JobStatus | None, Query(description="Only jobs in this state.")] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> JobsPublic:
    rows, count = store.list_jobs(owner, session, status, limit, offset)
    return JobsPublic(data=[job_public(r, live_product_names(data, r), engine_compiling(data, r)) for r in rows],
                      count=count)


@router.get("/{job_id}", response_model=JobPublic)
def get_job(job: JobDep, data: DataDep) -> JobPublic:
    """Status, progress (0..1, scans done/total), ETA, the error reason, and the products available."""
    return job_public(job, live_product_names(data, job), engine_compiling(data, job))


@router.delete("/{job_id}", response_model=JobPublic, status_code=202, responses={409: {"model": ErrorResponse}})
def cancel_job(job: JobDep, store: StoreDep, runner: RunnerDep, data: DataDep) -> JobPublic:
    """Cancel: a queued job at once, a running one within about a second (its worker checks the
    flag at every progress report; one that does not stop is terminated after a grace period)."""
    if not job.active:
        raise Conflict(f"job already {job.status}", {"status": job.status})
    store.request_cancel(job.id)
    runner.cancel(job.id)
    row = store.get_job(job.id) or job  # (deleted meanwhile: the job as it was)
    return job_public(row, live_product_names(data, row), engine_compiling(data, row))
