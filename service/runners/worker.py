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
import shutil
import signal
import time
import traceback
from pathlib import Path
from typing import Any

from api_schemas.jobs import JobStatus
from service.http_errors import is_disk_full, shorten_tokens
from service.jobs.context import JobContext, JobFailed, JobFunction
from service.jobs.events import job_event
from service.memory_watchdog import MemoryGuard, limit_reason
from service.process_guard import die_with_parent
from service.runners.heartbeat import with_heartbeat
from service.storage.data_dir import DataDir
from service.storage.disk_space import write_status
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
    Its peak memory is measured; past ``memory_limit_mb`` (0 = no limit) it fails with that reason.
    The job writes into a staging folder of its own, moved into the job's folder only while the job
    is still running on this process (:func:`publish`)."""
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
    staging = data.job_dir(job_id) / f"{STAGING_PREFIX}{os.getpid()}"
    ctx = JobContext(job_id=job_id, job=job, store=store, data=data, memory=guard, staging=staging)
    try:
        status, error = run_job_function(function, ctx, memory_limit_mb)
        moved = publish(store, data, job_id, staging) if status is JobStatus.SUCCEEDED else None
        if moved is None and status is JobStatus.SUCCEEDED:
            logger.warning("job %s is not this worker's any more: its products were discarded", job_id)
            current = store.get_job(job_id)
            return None if current is None else current.status
        if status is not JobStatus.SUCCEEDED:  # what it wrote is freed first: on a full disk, room for the status
            shutil.rmtree(staging, ignore_errors=True)
            data.remove(data.live_dir(job_id))  # served only while it runs: on a full disk, MBs a job held
        recorded = write_status(data, lambda: store.finish(job_id, status, error))
        if not recorded:  # failed or cancelled meanwhile: first writer wins
            for path in moved or []:
                if path.is_dir():
                    data.remove(path)
                else:
                    path.unlink(missing_ok=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
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


STAGING_PREFIX = ".staging-"  # + the worker's pid: a folder in the job's folder that one attempt writes into


def publish(store: JobStore, data: DataDir, job_id: str, staging: Path) -> list[Path] | None:
    """Move what an attempt wrote into ``staging`` into the job's folder, if the job is still running
    on this process (:meth:`JobStore.owns`); the paths moved in, or None when it is not (nothing moved:
    a worker never writes into a job that was failed as lost or interrupted, or cancelled)."""
    if not store.owns(job_id, os.getpid()):
        return None
    job_dir = data.job_dir(job_id)
    moved = []
    for entry in sorted(staging.iterdir()) if staging.is_dir() else []:
        target = job_dir / entry.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        os.replace(entry, target)
        moved.append(target)
    return moved


DISK_FULL_REASON = "disk full: the service's data folder has no space left for the job's products"


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
        if is_disk_full(exc, free_bytes=ctx.data.free_bytes()):  # the store raises its driver's errors
            logger.error("job %s: the disk is full: %s", ctx.job_id, exc)
            return JobStatus.FAILED, DISK_FULL_REASON
        logger.error("job %s crashed:\n%s", ctx.job_id, traceback.format_exc())
        return JobStatus.FAILED, internal_error(exc)
    return JobStatus.SUCCEEDED, None


def internal_error(exc: BaseException) -> str:
    """What a user sees of a failure inside the service: a generic reason and the error's class, never
    its text (which may name internal functions, memory addresses or server paths; the server's log
    has the traceback)."""
    return f"internal error ({type(exc).__name__}): the job failed inside the service; its log has the details"


def worker_main(data_root: str, store: JobStore, job_function: str, slot: int, inbox: Any, outbox: Any,
                memory_limit_mb: int = 0, heartbeat_s: float = 5.0, cancel_grace_s: float = 5.0) -> None:
    """Entry point of a spawned worker process: take job ids from ``inbox`` until ``None``.
    ``store`` is the server's (it holds only where the database is, no connection). The process
    dies with the server; each job writes a heartbeat every ``heartbeat_s`` while it runs."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which shuts us down
    die_with_parent()
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
    function = with_heartbeat(function, heartbeat_s, cancel_grace_s)
    while True:
        job_id = inbox.get()
        if job_id is None:
            return
        try:
            status, unwritten = execute_job(job_id, store, data, function, memory_limit_mb), None
        except Exception as exc:  # the store refused a write (a full disk, a locked database): the runner
            status, unwritten = JobStatus.FAILED, unwritten_reason(exc, data)  # writes the outcome instead
            logger.error("job %s: its status could not be written (%s: %s): left to the runner", job_id,
                         type(exc).__name__, exc)
        outbox.put((slot, job_id, status, unwritten))


def unwritten_reason(exc: BaseException, data: DataDir) -> str:
    """The failure a job gets when its worker could not write its outcome for ``exc``."""
    return DISK_FULL_REASON if is_disk_full(exc, free_bytes=data.free_bytes()) else internal_error(exc)
