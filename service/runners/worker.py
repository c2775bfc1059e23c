"""What runs inside a worker process: the job's status transitions around a job function.

A job function takes a :class:`~service.jobs.context.JobContext` and does the work (see there for
progress and cancel). The job function is named by a dotted path (``"package.module:function"``) so
that the spawned worker can import it; tests inject tiny ones.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import signal
import time
import traceback
from pathlib import Path
from typing import Any

from api_schemas.jobs import JobStatus
from service.http_errors import shorten_tokens
from service.jobs.context import JobContext, JobFailed, JobFunction
from service.jobs.events import job_event
from service.memory_watchdog import MemoryGuard, limit_reason
from service.storage.data_dir import DataDir
from service.storage.store import JobStore
from slam_engine.errors import Cancelled, LogFormatError, SlamEngineError

logger = logging.getLogger("lidarmap.worker")


def import_function(dotted: str) -> JobFunction:
    """``"package.module:function"`` -> the function."""
    module_name, _, name = dotted.partition(":")
    if not name:
        raise ValueError(f"job function must look like 'package.module:function', got {dotted!r}")
    return getattr(importlib.import_module(module_name), name)


def execute_job(job_id: str, store: JobStore, data: DataDir, function: JobFunction,
                memory_limit_mb: int = 0) -> JobStatus | None:
    """Run one job to a terminal status; returns that status, or None when the job was not queued any
    more (cancelled or deleted meanwhile: nothing ran). Never raises for the job's own errors.
    Its peak memory is measured; past ``memory_limit_mb`` (0 = no limit) it fails with that reason."""
    if not store.mark_running(job_id, os.getpid()):
        return None  # cancelled (or deleted) while queued
    job = store.get_job(job_id)
    if job is None:
        return None
    started_s = time.monotonic()
    queued_s = None if job.started_at is None else job.started_at - job.created_at
    job_event("started", job_id, worker_pid=os.getpid(), queued_s=queued_s)

    def fail_for_memory(reason: str) -> None:
        store.finish(job_id, JobStatus.FAILED, reason)

    guard = MemoryGuard(memory_limit_mb, on_exceeded=fail_for_memory)
    ctx = JobContext(job_id=job_id, job=job, store=store, data=data, memory=guard)
    status, error = run_job_function(function, ctx, memory_limit_mb)
    recorded = store.finish(job_id, status, error)
    row = store.get_job(job_id)
    if not recorded and row is not None:  # finished meanwhile by another (the memory guard, a reaper): its outcome
        status, error = row.status, row.error
    level = logging.WARNING if status is JobStatus.FAILED else logging.INFO
    job_event(status.value, job_id, level, duration_s=time.monotonic() - started_s,
              scans=None if row is None else row.scans_done, peak_memory_mb=_megabytes(ctx.peak_memory_bytes()),
              error=error)
    return status


def _megabytes(size: int | None) -> int | None:
    return None if size is None else round(size / 1024**2)


def run_job_function(function: JobFunction, ctx: JobContext, memory_limit_mb: int) -> tuple[JobStatus, str | None]:
    """The terminal status of ``function(ctx)`` and the error its user sees (None when it succeeded)."""

    def public(reason: str) -> str:  # no server paths, no quoted input of unbounded length
        return shorten_tokens(reason.replace(f"{ctx.data.root}/", ""))

    try:
        with ctx.memory or contextlib.nullcontext():
            function(ctx)
    except MemoryError:
        reason = limit_reason(memory_limit_mb) if memory_limit_mb else "out of memory"
        return JobStatus.FAILED, f"{reason} (an allocation was refused)"
    except Cancelled:
        return JobStatus.CANCELLED, "cancelled by request"
    except JobFailed as exc:
        return JobStatus.FAILED, public(str(exc))
    except LogFormatError as exc:
        where = f" ({exc.location})" if exc.location else ""
        return JobStatus.FAILED, public(f"log_format: {exc.message}{where}")
    except SlamEngineError as exc:
        return JobStatus.FAILED, public(f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # the job's bug must not kill the worker
        logger.error("job %s crashed:\n%s", ctx.job_id, traceback.format_exc())
        return JobStatus.FAILED, public(f"internal error: {type(exc).__name__}: {exc}")
    return JobStatus.SUCCEEDED, None


def worker_main(data_root: str, store: JobStore, job_function: str, slot: int, inbox: Any, outbox: Any,
                memory_limit_mb: int = 0) -> None:
    """Entry point of a spawned worker process: take job ids from ``inbox`` until ``None``.
    ``store`` is the server's (it holds only where the database is, no connection)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which shuts us down
    # several workers share the cores: one engine thread each unless LIDARMAP_THREADS says otherwise
    os.environ.setdefault("LIDARMAP_THREADS", "1")
    logging.basicConfig(level=logging.INFO, format="%(levelname)-9s %(message)s")  # as uvicorn's lines
    data = DataDir(Path(data_root))
    try:
        function = import_function(job_function)
    except Exception as exc:  # fail each job with the reason instead of dying (and being respawned) in a loop
        logger.error("cannot load job function %s:\n%s", job_function, traceback.format_exc())
        reason = f"worker cannot load the job function {job_function!r}: {type(exc).__name__}: {exc}"

        def function(ctx: JobContext) -> None:
            raise RuntimeError(reason)
    while True:
        job_id = inbox.get()
        if job_id is None:
            return
        status = execute_job(job_id, store, data, function, memory_limit_mb)
        outbox.put((slot, job_id, status))
