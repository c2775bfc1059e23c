"""Mapping jobs: a SLAM run over a session's log or stream, with its progress and products."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class JobStatus(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class JobSource(StrEnum):
    LOG = "log"  # an uploaded log (the newest one unless log_id is given)
    STREAM = "stream"  # the streamed chunks 0..k received when the job starts


class JobCreate(BaseModel):
    """Run parameters; every one bounded so a run's cost is finite."""

    model_config = ConfigDict(extra="forbid")

    source: JobSource | None = Field(None, description="Default: 'log' if the session has an upload, "
                                     "else 'stream'.")
    log_id: str | None = Field(None, max_length=64, description="Which upload (default: the newest).")
    particles: int = Field(30, ge=1, le=1000)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    resolution_m: float = Field(0.05, ge=0.01, le=1.0, description="Grid cell size [m].")
    max_range_m: float = Field(30.0, gt=0.1, le=200.0, description="Beams are used up to this range [m].")
    linear_update_m: float = Field(0.2, ge=0.0, le=10.0, description="Process a scan after this much travel [m].")
    angular_update_rad: float = Field(0.1, ge=0.0, le=3.2, description="... or this much rotation [rad].")
    snapshot_every_scans: int = Field(50, ge=0, le=100_000, description="Live map preview and animation "
                                      "frame every n processed scans (0 = none).")


class JobPublic(BaseModel):
    id: str
    session_id: str
    source: JobSource
    log_id: str | None
    status: JobStatus
    progress: float = Field(ge=0.0, le=1.0)
    scans_done: int
    scans_total: int | None
    eta_s: float | None = Field(description="Estimated seconds left while running.")
    error: str | None = Field(description="Why the job failed or was cancelled.")
    cancel_requested: bool
    config: dict[str, Any] = Field(description="The parameters the job was created with.")
    input: dict[str, Any] | None = Field(description="What the job mapped (log summary; chunks used).")
    products: list[str] = Field(description="Product names available now, e.g. 'occupancy.png'.")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int
