"""One job as its job function sees it (:class:`JobContext`), and how the function says it failed.

A job function takes a :class:`JobContext` and does the work; it reports progress through
``ctx.progress(...)`` (or a run's ``RunProgress`` through ``ctx.run_progress``), which writes the job
store (throttled), records the stage the job is in (a file in its folder, :data:`STAGE_FILE`; logged
when it changes) and raises :class:`~slam_engine.errors.Cancelled` once a cancel was requested, so a
run stops within one progress interval. The worker (:mod:`service.runners.worker`) runs it and
records the outcome.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from service.jobs.events import job_event
from service.memory_watchdog import MemoryGuard
from service.storage.data_dir import DataDir, write_atomic
from service.storage.rows import JobRow
from service.storage.store import JobStore
from slam_engine.errors import Cancelled
from slam_engine.progress import RunProgress, run_fraction

PROGRESS_INTERVAL_S = 0.2
STAGE_FILE = "stage"  # in the job's folder: the stage a running job is in (e.g. "closing loops")

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
    _stage: str | None = field(default=None, repr=False)
    _started_s: float = field(default_factory=time.monotonic, repr=False)

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

    def progress(self, scans_done: int, scans_total: int | None, force: bool = False, stage: str | None = None,
                 fraction: float | None = None) -> None:
        """Record progress at most every PROGRESS_INTERVAL_S (a new ``stage`` at once); raise Cancelled
        when asked to stop. ``fraction``: the whole job's share done (default: the scans' share)."""
        now = time.monotonic()
        new_stage = stage is not None and stage != self._stage
        if not force and not new_stage and now - self._last_write_s < PROGRESS_INTERVAL_S:
            return
        self._last_write_s = now
        if new_stage:
            assert stage is not None
            self._stage = stage
            write_atomic(self.data.job_dir(self.job_id) / STAGE_FILE, stage.encode())  # not staged: read live
            job_event("stage", self.job_id, stage=stage, progress=fraction, elapsed_s=now - self._started_s)
        if self.store.update_progress(self.job_id, scans_done, scans_total, fraction):
            raise Cancelled("cancelled by request")

    def run_progress(self, progress: RunProgress) -> None:
        """Record a run's progress report (its stage and share done)."""
        self.progress(progress.scans_done, progress.scans_total, stage=progress.stage, fraction=progress.fraction)

    def stage(self, stage: str, stage_fraction: float = 0.0) -> None:
        """Record that the job is in ``stage`` (e.g. writing its products), its scans unchanged."""
        job = self.store.get_job(self.job_id)
        done, total = (0, None) if job is None else (job.scans_done, job.scans_total)
        self.progress(done, total, force=True, stage=stage, fraction=run_fraction(stage, stage_fraction))

    def check_cancel(self) -> None:
        """Raise Cancelled when a cancel was requested (for steps without progress counts)."""
        if self.store.cancel_requested(self.job_id):
            raise Cancelled("cancelled by request")
