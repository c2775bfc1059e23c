"""One job as its job function sees it (:class:`JobContext`), and how the function says it failed.

A job function takes a :class:`JobContext` and does the work; it reports progress through
``ctx.progress(...)``, which writes the job store (throttled) and raises
:class:`~slam_engine.errors.Cancelled` once a cancel was requested, so a run stops within one
progress interval. The worker (:mod:`service.runners.worker`) runs it and records the outcome.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from service.memory_watchdog import MemoryGuard
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow
from service.storage.store import JobStore
from slam_engine.errors import Cancelled

PROGRESS_INTERVAL_S = 0.2

JobFunction = Callable[["JobContext"], None]


class JobFailed(Exception):
    """A job function's own failure, with the reason the user sees as the job's error."""


@dataclass
class JobContext:
    """One job as its function sees it: the stored row, the store, the data folder, progress."""

    job_id: str
    job: JobRow
    store: JobStore
    data: DataDir
    memory: MemoryGuard | None = field(default=None, repr=False)
    staging: Path | None = field(default=None, repr=False)
    _last_write_s: float = field(default=0.0, repr=False)

    def peak_memory_bytes(self) -> int | None:
        """The job's peak resident memory so far [bytes] (None when not measured)."""
        return None if self.memory is None else self.memory.peak_bytes()

    @property
    def out_dir(self) -> Path:
        """Where the job writes its artifacts (created): this attempt's ``staging`` folder, moved into the
        job's folder only while the job is still this worker's (:func:`service.runners.worker.publish`),
        or the job's folder itself when there is none."""
        path = self.staging or self.data.job_dir(self.job_id)
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
