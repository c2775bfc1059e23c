"""Store rows -> public schemas (times as UTC datetimes, ETA from progress)."""

from __future__ import annotations

import time
from datetime import UTC, datetime

from api_schemas.jobs import JobMode, JobPublic, JobStatus
from api_schemas.logs import LogPublic
from api_schemas.sessions import SessionPublic
from service.storage.rows import JobRow, LogRow, SessionRow


def utc(ts: float | None) -> datetime | None:
    return None if ts is None else datetime.fromtimestamp(ts, tz=UTC)


def session_public(row: SessionRow) -> SessionPublic:
    return SessionPublic.model_validate({
        "id": row.id, "name": row.name, "vehicle_preset": row.vehicle_preset, "calibration": row.calibration,
        "geo": row.geo, "created_at": utc(row.created_at), "logs": row.logs, "chunks": row.chunks, "jobs": row.jobs})


def log_public(row: LogRow) -> LogPublic:
    return LogPublic(id=row.id, session_id=row.session_id, filename=row.filename, size_bytes=row.size_bytes,
                     sha256=row.sha256, archive=row.archive, summary=row.summary, created_at=utc(row.created_at))


def eta_s(row: JobRow, now: float | None = None) -> float | None:
    """Seconds left, extrapolating the time the share done so far took (every stage: mapping, back end,
    products); None when unknown."""
    if row.status is not JobStatus.RUNNING or not row.started_at or row.live or row.progress <= 0.0:
        return None
    elapsed = (now or time.time()) - row.started_at
    return max(0.0, elapsed * (1.0 - row.progress) / row.progress)


def job_public(row: JobRow, live_products: list[str] | None = None, compiling: bool = False,
               stage: str | None = None, include_config: bool = True) -> JobPublic:
    """The public view of a job row; ``compiling``: its engine is compiling (no ETA meanwhile); ``stage``:
    what a running job does now; its settings (``config``) only with ``include_config``."""
    products = sorted(set(row.products) | set(live_products or []))
    following = row.live and row.status is not JobStatus.SUCCEEDED  # total unknown
    slam = row.config.get("slam") or {}
    return JobPublic(id=row.id, session_id=row.session_id, source=row.source, log_id=row.log_id, status=row.status,
                     mode=row.config.get("mode") or JobMode.MAP, map_job_id=row.config.get("map_job_id"),
                     merge_job_id=row.config.get("merge_job_id"),
                     live=row.live, particles=slam.get("particles", row.config.get("particles")),
                     stage=stage if row.status is JobStatus.RUNNING else None,
                     progress=None if following else row.progress, scans_done=row.scans_done,
                     scans_total=row.scans_total, eta_s=None if compiling else eta_s(row), compiling=compiling,
                     error=row.error, cancel_requested=row.cancel_requested,
                     config=row.config if include_config else None, input=row.input,
                     products=products, created_at=utc(row.created_at), started_at=utc(row.started_at),
                     finished_at=utc(row.finished_at))
