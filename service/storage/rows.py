"""The job store's rows, typed: what :class:`~service.storage.store.JobStore` hands out.

Frozen dataclasses, built from the database's columns in one place each (``from_db``): JSON columns
decoded, SQLite's 0/1 flags as booleans, statuses and sources as the API's enums. A row is a snapshot
of one transaction; read the store again for the state now.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from api_schemas.jobs import JobSource, JobStatus

ACTIVE_STATUSES = (JobStatus.QUEUED, JobStatus.RUNNING)
TERMINAL_STATUSES = (JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED)


def dump_json(value: Any) -> str | None:
    """A JSON column's text (None stays NULL)."""
    return None if value is None else json.dumps(value, sort_keys=True)


def load_json(text: str | None) -> Any:
    return None if text is None else json.loads(text)


@dataclass(frozen=True)
class SessionRow:
    """A session with the counts of what it holds."""

    id: str
    owner: str
    name: str
    vehicle_preset: str | None
    calibration: dict[str, Any] | None  # the vehicle (and LiDAR) as SessionCreate's calibration
    geo: dict[str, Any] | None  # lat_deg, lon_deg, heading_deg of the map's origin
    created_at: float
    logs: int
    chunks: int
    jobs: int

    @classmethod
    def from_db(cls, d: Mapping[Any, Any]) -> SessionRow:
        return cls(id=d["id"], owner=d["owner"], name=d["name"], vehicle_preset=d["vehicle_preset"],
                   calibration=load_json(d["calibration_json"]), geo=load_json(d["geo_json"]),
                   created_at=float(d["created_at"]), logs=int(d["n_logs"]), chunks=int(d["n_chunks"]),
                   jobs=int(d["n_jobs"]))


@dataclass(frozen=True)
class LogRow:
    """An uploaded log, checked on arrival."""

    id: str
    session_id: str
    filename: str
    size_bytes: int
    sha256: str
    archive: bool  # a zipped folder, extracted under the upload's folder
    summary: dict[str, Any]  # the loader's summary (format, streams, duration, ...)
    stored_path: str  # relative to the data folder
    created_at: float

    @classmethod
    def from_db(cls, d: Mapping[Any, Any]) -> LogRow:
        return cls(id=d["id"], session_id=d["session_id"], filename=d["filename"], size_bytes=int(d["size_bytes"]),
                   sha256=d["sha256"], archive=bool(d["archive"]), summary=load_json(d["summary_json"]) or {},
                   stored_path=d["stored_path"], created_at=float(d["created_at"]))


@dataclass(frozen=True)
class ChunkRow:
    """A streamed chunk (its messages lie in the data folder)."""

    session_id: str
    seq: int
    sha256: str
    messages: int
    t_first_s: float
    t_last_s: float
    created_at: float

    @classmethod
    def from_db(cls, d: Mapping[Any, Any]) -> ChunkRow:
        return cls(session_id=d["session_id"], seq=int(d["seq"]), sha256=d["sha256"], messages=int(d["messages"]),
                   t_first_s=float(d["t_first_s"]), t_last_s=float(d["t_last_s"]),
                   created_at=float(d["created_at"]))


@dataclass(frozen=True)
class JobRow:
    """A job: what it maps, its settings, where it stands, what it made."""

    id: str
    session_id: str
    owner: str
    source: JobSource
    log_id: str | None
    config: dict[str, Any]  # the settings as stored (service.jobs.settings reads them into a SlamConfig)
    status: JobStatus
    progress: float
    scans_done: int
    scans_total: int | None
    error: str | None
    cancel_requested: bool
    input: dict[str, Any] | None  # what the job mapped, recorded by its worker
    products: dict[str, str]  # product name -> file inside the job's folder
    worker_pid: int | None
    created_at: float
    started_at: float | None
    finished_at: float | None
    heartbeat_at: float | None

    @property
    def active(self) -> bool:
        """Queued or running."""
        return self.status in ACTIVE_STATUSES

    @property
    def live(self) -> bool:
        """A live job: it follows its session's stream."""
        return bool(self.config.get("live"))

    @classmethod
    def from_db(cls, d: Mapping[Any, Any]) -> JobRow:
        return cls(id=d["id"], session_id=d["session_id"], owner=d["owner"], source=JobSource(d["source"]),
                   log_id=d["log_id"], config=load_json(d["config_json"]) or {}, status=JobStatus(d["status"]),
                   progress=float(d["progress"]), scans_done=int(d["scans_done"]),
                   scans_total=_int_or_none(d["scans_total"]), error=d["error"],
                   cancel_requested=bool(d["cancel_requested"]), input=load_json(d["input_json"]),
                   products=load_json(d["products_json"]) or {}, worker_pid=_int_or_none(d["worker_pid"]),
                   created_at=float(d["created_at"]), started_at=_float_or_none(d["started_at"]),
                   finished_at=_float_or_none(d["finished_at"]), heartbeat_at=_float_or_none(d["heartbeat_at"]))


@dataclass(frozen=True)
class StreamFigures:
    """A stream's state as SQL computes it (cheap for long streams)."""

    received: int  # chunks received
    contiguous_through: int  # the end of the run of seqs from 0 (-1: no chunk 0)
    messages: int  # messages in that run
    highest: int  # the highest seq received (-1: none)
    after: list[int]  # seqs received beyond the run, ascending (at most the store's max_after)
    last_seq: int | None  # the finished stream's last seq (None while open)


def _int_or_none(value: Any) -> int | None:
    return None if value is None else int(value)


def _float_or_none(value: Any) -> float | None:
    return None if value is None else float(value)
