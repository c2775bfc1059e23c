"""Creating a job: what it maps, whether it may start, and what it may cost - the rules behind
POST /v1/sessions/{id}/jobs (the route only hands over and answers)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from api_schemas.jobs import JobMode, JobSource
from service.http_errors import Conflict, InvalidInput, NotFound
from service.jobs.estimate import (
    check_drive_memory,
    check_job_memory,
    drive_estimate,
    estimate_bytes,
    stored_figures,
)
from service.jobs.events import job_event
from service.jobs.saved_maps import saved_map_path, saved_map_paths
from service.jobs.settings import JobSettings, resolve, stored_config
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow, SessionRow
from service.storage.store import JobStore
from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError


def create_job(body: JobSettings, session: SessionRow, store: JobStore, data: DataDir, submit: Callable[[str], None],
               limit_mb: int) -> JobRow:
    """Validate ``body`` for ``session``, store the job and ``submit`` it (by id) to the runner.

    422: settings out of the engine's bounds, or clearly needing more than ``limit_mb``; 404: an
    unknown ``log_id`` or ``map_job_id``; 409: nothing to map (no upload, no chunks, no calibration for
    a stream), a saved map not finished yet, or a second live job in the session."""
    slam = resolve(body)  # the engine's bounds: 422 naming the setting
    config = stored_config(body, slam)
    if body.mode is JobMode.MERGE:  # two saved maps in, no drive: 404 / 409 now, not when the job runs
        assert body.map_job_id is not None and body.merge_job_id is not None  # JobCreate checked both
        saved_map_path(store, data, session.owner, body.map_job_id)
        saved_map_path(store, data, session.owner, body.merge_job_id, field="merge_job_id")
        row = store.create_job(session.id, session.owner, JobSource.MAP, None, config)
        job_event("created", row.id, session=session.id, source=row.source.value, mode=config.get("mode"))
        submit(row.id)
        return row
    source = input_source(body, session)
    log_id = None if source is JobSource.STREAM else input_log(body, session, store)
    # an upload's scan count and extent are known up front; every job checks again once its input is read
    summary = {} if log_id is None else _summary_of(store, log_id, session.id)
    scans = summary.get("streams", {}).get("scans")
    refuse_costly_job(slam, scans, limit_mb)
    refuse_costly_drive(slam, summary, scans, limit_mb)
    if body.map_job_id is not None:
        saved_map_path(store, data, session.owner, body.map_job_id)  # 404 / 409 now, not when the job runs
    elif body.mode is JobMode.LOCALIZE:
        saved_map_paths(store, data, session.owner)  # 409 now when the key has no saved map at all
    if body.live:
        row = _live_job(config, session, store)
    else:
        if source is JobSource.STREAM:
            _stream_ready(session)
        row = store.create_job(session.id, session.owner, source, log_id, config)
    job_event("created", row.id, session=session.id, source=row.source.value, live=row.live or None,
              mode=config.get("mode"))
    submit(row.id)
    return row


def input_source(body: JobSettings, session: SessionRow) -> JobSource:
    """What the job maps: as asked, else the session's upload when it has one, else its stream (a live
    job always follows the stream)."""
    if body.live:
        return JobSource.STREAM
    return body.source or (JobSource.LOG if session.logs else JobSource.STREAM)


def input_log(body: JobSettings, session: SessionRow, store: JobStore) -> str:
    """The upload a log job maps: ``log_id`` (404 when unknown) or the session's newest (409 with none)."""
    if body.log_id is not None:
        if store.get_log(body.log_id, session.id) is None:
            raise NotFound(f"no log {body.log_id!r} in this session", {"field": "log_id"})
        return body.log_id
    newest = store.list_logs(session.id)
    if not newest:
        raise Conflict("the session has no uploaded log: POST one to /v1/sessions/{id}/logs first",
                       {"session_id": session.id})
    return newest[0].id


def _summary_of(store: JobStore, log_id: str, session_id: str) -> dict[str, Any]:
    row = store.get_log(log_id, session_id)
    return {} if row is None else row.summary


def refuse_costly_job(config: SlamConfig, scans: int | None, limit_mb: int) -> None:
    """422 with the estimate when ``config`` clearly needs more than ``limit_mb``."""
    try:
        check_job_memory(config, scans, limit_mb)
    except ConfigError as exc:
        err = InvalidInput(str(exc), {"limit_mb": limit_mb, **estimate_bytes(config, scans)})
        err.code = "job_too_large"
        raise err from None


def refuse_costly_drive(config: SlamConfig, summary: dict[str, Any], scans: int | None, limit_mb: int) -> None:
    """422 with the estimate when mapping the uploaded drive (its extent and scans, as its inspection
    measured them) is estimated to need more than ``limit_mb``."""
    figures = stored_figures(summary)
    if figures is None:
        return
    try:
        check_drive_memory(config, figures, scans, limit_mb)
    except ConfigError as exc:
        err = InvalidInput(str(exc), {"limit_mb": limit_mb, **drive_estimate(config, figures)})
        err.code = "job_too_large"
        raise err from None


def _stream_ready(session: SessionRow) -> dict[str, Any]:
    """The session's calibration, which streamed chunks need; 409 without chunks or calibration."""
    if not session.chunks:
        raise Conflict("the session has no streamed chunks: POST some to /v1/sessions/{id}/chunks first "
                       "(or start a live job, which waits for them)", {"session_id": session.id})
    return stream_calibration(session)


def stream_calibration(session: SessionRow) -> dict[str, Any]:
    """The session's calibration, which streamed chunks need (409 without one)."""
    if session.calibration is None:
        raise Conflict("streamed chunks need the vehicle's calibration: create the session with "
                       "'calibration'", {"session_id": session.id})
    return session.calibration


def _live_job(config: dict[str, Any], session: SessionRow, store: JobStore) -> JobRow:
    """A live job: one per session, with a calibration that has a LiDAR (409 otherwise)."""
    if stream_calibration(session).get("lidar") is None:
        raise Conflict("a live job maps LiDAR scans as they arrive: the session's calibration needs 'lidar'",
                       {"session_id": session.id})
    row, active = store.create_live_job(session.id, session.owner, config)
    if row is None:
        assert active is not None  # no new row: because of this active live job
        raise Conflict(f"the session already has a live job ({active.id}, {active.status}): one live job per "
                       "session; cancel it or finish the stream first", {"job_id": active.id})
    return row
