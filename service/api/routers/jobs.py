"""Jobs: create (on a session), list, read, cancel."""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Any

from fastapi import APIRouter, Query

from api_schemas.error_body import ErrorResponse
from api_schemas.jobs import JobPublic, JobsPublic, JobStatus
from service.api.convert import job_public
from service.api.deps import MAX_OFFSET, DataDep, JobDep, OwnerDep, RunnerDep, SessionDep, SettingsDep, StoreDep
from service.http_errors import Conflict
from service.jobs.creation import create_job as create
from service.jobs.events import job_event
from service.jobs.products import engine_compiling, live_product_names, running_stage
from service.jobs.settings import JobSettings
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow

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
    session; the session may have no chunks yet). With ``mode`` 'localize' or 'extend' and ``map_job_id``
    the job starts from that finished job's saved map. Poll GET /v1/jobs/{id}. 422 when the parameters
    clearly need more memory than the job memory limit (the estimate in the detail)."""
    return job_public(create(body, session, store, data, runner.submit, settings.job_memory_limit()))


class Include(StrEnum):
    CONFIG = "config"


IncludeQuery = Annotated[list[Include], Query(max_length=1, description="'config': also the job's settings "
                                                                         "(the whole engine configuration, ~3 KB).")]


def public(row: JobRow, data: DataDir, include: list[Include] | None = None) -> JobPublic:
    """A job as the API shows it now: live products, compiling, stage; its settings only when asked."""
    return job_public(row, live_product_names(data, row), engine_compiling(data, row), running_stage(data, row),
                      include_config=Include.CONFIG in (include or []))


@router.get("", response_model=JobsPublic)
def list_jobs(store: StoreDep, owner: OwnerDep, data: DataDep,
              session: Annotated[str | None, Query(max_length=64, description="Only this session's jobs.")] = None,
              status: Annotated[JobStatus | None, Query(description="Only jobs in this state.")] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
              include: IncludeQuery = []) -> JobsPublic:  # noqa: B006 (FastAPI copies the default)
    rows, count = store.list_jobs(owner, session, status, limit, offset)
    return JobsPublic(data=[public(r, data, include) for r in rows], count=count)


@router.get("/{job_id}", response_model=JobPublic)
@router.head("/{job_id}", response_model=JobPublic, name="get_job (head)")
def get_job(job: JobDep, data: DataDep, include: IncludeQuery = []) -> JobPublic:  # noqa: B006
    """Status, stage, progress (0..1 over every stage; scans done/total), ETA, the error reason, and the
    products available. The job's settings only with ``?include=config``."""
    return public(job, data, include)


@router.delete("/{job_id}", response_model=JobPublic, status_code=202, responses={409: {"model": ErrorResponse}})
def cancel_job(job: JobDep, store: StoreDep, runner: RunnerDep, data: DataDep) -> JobPublic:
    """Cancel: a queued job at once, a running one within about a second (its worker checks the
    flag at every progress report; one that does not stop is terminated after a grace period)."""
    if not job.active:
        raise Conflict(f"job already {job.status}", {"status": job.status})
    if store.request_cancel(job.id) is JobStatus.CANCELLED:  # it was queued: cancelled now, never ran
        job_event(JobStatus.CANCELLED.value, job.id, error="cancelled by request")
    runner.cancel(job.id)
    row = store.get_job(job.id) or job  # (deleted meanwhile: the job as it was)
    return public(row, data)
