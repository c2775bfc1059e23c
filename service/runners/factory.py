"""The job runner the settings ask for: local worker processes, or Celery (an optional dependency,
imported only when asked for)."""

from __future__ import annotations

from typing import Any

from service.runners.base import DEFAULT_JOB_FUNCTION, JobRunner
from service.runners.local import LocalProcessRunner
from service.storage.data_dir import DataDir
from service.storage.store import JobStore


def create_runner(settings: Any, data: DataDir, store: JobStore, job_function: str | None = None) -> JobRunner:
    """The runner the settings ask for."""
    if settings.runner == "local":
        return LocalProcessRunner(data, store, settings.workers, settings.cancel_grace_s,
                                  job_function or DEFAULT_JOB_FUNCTION,
                                  memory_limit_mb=settings.job_memory_limit(), heartbeat_s=settings.heartbeat_s,
                                  worker_lost_s=settings.worker_lost_s, max_jobs_per_worker=settings.worker_max_jobs)
    if settings.runner == "celery":
        from service.runners.celery_runner import CeleryRunner  # celery is an optional dependency

        return CeleryRunner(settings, data, store)
    raise ValueError(f"unknown runner {settings.runner!r}")
