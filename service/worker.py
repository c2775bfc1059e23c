"""What runs inside a worker process: the job's status transitions around a job function.

A job function takes a :class:`JobContext` and does the work; it reports progress through
``ctx.progress(...)``, which writes the job store (throttled) and raises
:class:`~slam_engine.errors.Cancelled` once a cancel was requested, so a run stops within one
progress interval. The job function is named by a dotted path (``"package.module:function"``) so
that the spawned worker can import it; tests inject tiny ones.
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.errors import shorten_tokens
from service.job_memory import MemoryGuard, limit_reason
from service.storage import DataDir
from service.store import JobStore
from slam_engine.errors import Cancelled, LogFormatError, SlamEngineError

logger = logging.getLogger("lidarmap.worker")

PROGRESS_INTERVAL_S = 0.2

JobFunction = Callable[["JobContext"], None]


class JobFailed(Exception):
    """A job function's own failure, with the reason the user sees as the job's error."""


@dataclass
class JobContext:
    """One job as its function sees it: the stored row, the store, the data folder, progress."""

    job_id: str
    job: dict[str, Any]
    store: JobStore
    data: DataDir
    memory: MemoryGuard | None = field(default=None, repr=False)
    _last_write_s: float = field(default=0.0, repr=False)

    def peak_memory_bytes(self) -> int | None:
        """The job's peak resident memory so far [bytes] (None when not measured)."""
        return None if self.memory is None else self.memory.peak_bytes()

    @property
    def out_dir(self) -> Path:
        """The job's artifact folder (created)."""
        path = self.data.job_dir(self.job_id)
        path.mkdir(parents=True, exist_ok=True)
        return path

    def progress(self, scans_done: int, scans_total: int | None, force: bool = False) -> None:
        """Record progress at most every PROGRESS_INTERVAL_S; raise Cancelled when asked to stop."""
        now = time.monotonic()
        if not force and now - self._last_write_s < PROGRESS_INTERVAL_S:
            return
        self._last_write_s = now
        if self.store.update_progress(self.job_id, scans_done, scans_total):
            raise Cancelled("cancelled by request")

    def check_cancel(self) -> None:
        """Raise Cancelled when a cancel was requested (for steps without progress counts)."""
        if self.store.cancel_requested(self.job_id):
            raise Cancelled("cancelled by request")


def import_function(dotted: str) -> JobFunction:
    """``"package.module:function"`` -> the function."""
    module_name, _, name = dotted.partition(":")
    if not name:
        raise ValueError(f"job function must look like 'package.module:function', got {dotted!r}")
    return getattr(importlib.import_module(module_name), name)


def execute_job(job_id: str, store: JobStore, data: DataDir, function: JobFunction,
                memory_limit_mb: int = 0) -> str:
    """Run one job to a terminal status; returns that status. Never raises for the job's own errors.
    Its peak memory is measured; past ``memory_limit_mb`` (0 = no limit) it fails with that reason."""
    if not store.mark_running(job_id, os.getpid()):
        return "skipped"  # cancelled (or deleted) while queued
    job = store.get_job(job_id)
    if job is None:
        return "skipped"
    def fail_for_memory(reason: str) -> None:
        store.finish(job_id, "failed", reason)

    guard = MemoryGuard(memory_limit_mb, on_exceeded=fail_for_memory)

    def public(reason: str) -> str:  # no server paths, no quoted input of unbounded length
        return shorten_tokens(reason.replace(f"{data.root}/", ""))

    ctx = JobContext(job_id=job_id, job=job, store=store, data=data, memory=guard)
    try:
        with guard:
            function(ctx)
    except MemoryError:
        reason = limit_reason(memory_limit_mb) if memory_limit_mb else "out of memory"
        store.finish(job_id, "failed", f"{reason} (an allocation was refused)")
        return "failed"
    except Cancelled:
        store.finish(job_id, "cancelled", "cancelled by request")
        return "cancelled"
    except JobFailed as exc:
        store.finish(job_id, "failed", public(str(exc)))
        return "failed"
    except LogFormatError as exc:
        where = f" ({exc.location})" if exc.location else ""
        store.finish(job_id, "failed", public(f"log_format: {exc.message}{where}"))
        return "failed"
    except SlamEngineError as exc:
        store.finish(job_id, "failed", public(f"{type(exc).__name__}: {exc}"))
        return "failed"
    except Exception as exc:  # the job's bug must not kill the worker
        logger.error("job %s crashed:\n%s", job_id, traceback.format_exc())
        store.finish(job_id, "failed", public(f"internal error: {type(exc).__name__}: {exc}"))
        return "failed"
    store.finish(job_id, "succeeded")
    return "succeeded"


def worker_main(data_root: str, store: JobStore, job_function: str, slot: int, inbox: Any, outbox: Any,
                memory_limit_mb: int = 0) -> None:
    """Entry point of a spawned worker process: take job ids from ``inbox`` until ``None``.
    ``store`` is the server's (it holds only where the database is, no connection)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which shuts us down
    # several workers share the cores: one engine thread each unless LIDARMAP_THREADS says otherwise
    os.environ.setdefault("LIDARMAP_THREADS", "1")
    logging.basicConfig(level=logging.INFO)
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
