"""Uploaded drive logs and the formats the service reads."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class LogSummary(BaseModel):
    """What the loader found in a log (``DriveLog.summary()``)."""

    format: str
    vehicle: str
    streams: dict[str, int] = Field(description="Stream name -> message count.")
    time_span_s: list[float] | None = Field(description="[first, last] timestamp [s].")
    duration_s: float | None
    lidar_beams: int | None
    warnings: list[str]


class LogPublic(BaseModel):
    id: str
    session_id: str
    filename: str = Field(description="The name the client gave (display only; never used as a path).")
    size_bytes: int
    sha256: str
    archive: bool = Field(description="Uploaded as a zip of a folder format and extracted.")
    summary: LogSummary
    created_at: datetime


class LogsPublic(BaseModel):
    data: list[LogPublic]
    count: int


class FormatPublic(BaseModel):
    name: str
    description: str
    can_write: bool


class FormatsPublic(BaseModel):
    data: list[FormatPublic]
    count: int
