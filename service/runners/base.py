"""What the API needs from a job runner (:class:`JobRunner`), the health it reports, and the job
function workers run unless told otherwise. Every runner implements this; none imports another."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

DEFAULT_JOB_FUNCTION = "service.jobs.mapping:run_mapping_job"


@dataclass(frozen=True)
class RunnerHealth:
    runner: str
    workers_total: int
    workers_alive: int
    busy: int
    queued: int

    @property
    def ready(self) -> bool:
        """Every worker the runner keeps is alive (a local runner with a worker missing is not ready: it
        said ready with 1 of 2 alive while jobs waited); a Celery runner counts those that answer."""
        return self.workers_alive > 0 and self.workers_alive >= self.workers_total


class JobRunner(Protocol):
    """What the API needs from a runner (a Celery runner can implement the same four calls)."""

    def submit(self, job_id: str) -> None:
        """Queue a job that is 'queued' in the store."""

    def cancel(self, job_id: str) -> None:
        """Make sure a job whose cancel flag is set in the store stops (the flag is the request)."""

    def shutdown(self) -> None:
        """Stop the workers; jobs still running are failed as interrupted."""

    def health(self) -> RunnerHealth:
        """Worker state for /readyz."""
