"""Service settings from the environment (prefix ``LIDARMAP_``), validated on creation."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Embedded defaults: SQLite, local disk and local worker processes, no external server."""

    model_config = SettingsConfigDict(env_prefix="LIDARMAP_", extra="ignore")

    data_dir: Path = Field(Path("lidarmap-data"), description="Where the job store, uploads and "
                           "artifacts live.")
    workers: int = Field(2, ge=1, le=64, description="Local SLAM worker processes.")
    worker_max_jobs: int = Field(1, ge=0, le=1_000_000, description="A worker process is replaced by a fresh "
                                 "one after this many jobs (0 = never), so an idle worker does not keep the memory "
                                 "its jobs left behind (measured after a 300-scan job: about 280 MB kept, 140 MB "
                                 "fresh). A Celery worker's pool process likewise (max tasks per child).")
    runner: Literal["local", "celery"] = Field("local", description="Job runner: 'local' worker processes, "
                                               "or 'celery' (jobs go through the broker to `lidarmap worker`s).")
    broker_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker (runner 'celery').")
    queue: str = Field("lidarmap", min_length=1, max_length=200, pattern=r"^[A-Za-z0-9_.:-]+$",
                       description="Celery queue the API sends jobs to and workers consume by default.")
    database_url: str = Field("", description="Job store: empty = SQLite in the data folder (one host), "
                              "sqlite:////absolute/path.sqlite3, or postgresql://user:password@host:5432/db "
                              "(API and workers on several hosts).", repr=False)
    heartbeat_s: float = Field(5.0, ge=0.1, le=300.0, description="How often [s] a running job's worker "
                               "(local or Celery) writes its heartbeat to the store.")
    worker_lost_s: float = Field(60.0, ge=1.0, le=86_400.0, description="A running job whose heartbeat is "
                                 "older than this [s] is failed as 'worker lost' (its worker stopped, hung or "
                                 "gone); a local worker is then killed and replaced.")
    max_upload_bytes: int = Field(2 * 1024**3, ge=1024, le=1024**4, description="Largest accepted upload.")
    max_zip_entries: int = Field(100_000, ge=1, le=10_000_000, description="Most files in an uploaded zip.")
    max_extracted_bytes: int = Field(8 * 1024**3, ge=1024, le=4 * 1024**4,
                                     description="Largest total size of an uploaded zip once extracted, "
                                     "or of a gzipped log once inflated.")
    max_zip_ratio: int = Field(100, ge=1, le=100_000, description="An uploaded zip whose members declare more "
                               "than this many times its own size once extracted (past 64 MiB) is refused (413) "
                               "before anything is written: a zip bomb.")
    inspection_memory_limit_mb: int = Field(2048, ge=128, le=1024**2, description="Memory [MB] one upload's "
                                            "inspection (loading the log to check it) may use; past it: 422.")
    inspection_timeout_s: float = Field(120.0, ge=1.0, le=86_400.0, description="Time one upload's "
                                        "inspection may take; past it the inspecting process is killed: 422.")
    inspection_processes: int = Field(2, ge=1, le=64, description="Uploads inspected at once (one process "
                                      "each); more wait their turn.")
    inspection_express_bytes: int = Field(4 * 1024**2, ge=0, le=1024**3, description="Uploads up to this size "
                                          "[bytes] once inflated may be inspected in one more process, the express "
                                          "lane, when every other is busy (0 = no express lane).")
    inspection_express_timeout_s: float = Field(10.0, ge=0.5, le=600.0, description="Time [s] one upload may "
                                                "take in the express lane; past it, it is inspected again in a "
                                                "regular lane.")
    max_chunk_bytes: int = Field(16 * 1024**2, ge=1024, le=1024**3, description="Largest streamed chunk body "
                                 "(and any other JSON body); the API holds about 8 times this while it parses one.")
    body_stall_timeout_s: float = Field(60.0, ge=0.5, le=3600.0, description="A request whose body gets no "
                                        "data for this long [s] is answered 408 and closed.")
    cancel_grace_s: float = Field(5.0, ge=0.1, le=600.0, description="A running job that ignores a cancel "
                                  "this long has its worker process terminated.")
    min_free_bytes: int = Field(256 * 1024**2, ge=0, le=1024**4, description="Disk space kept free: an "
                                "upload or chunk that would leave less answers 507 and stores nothing.")
    job_memory_limit_mb: int | None = Field(None, ge=0, le=1024**2, description="A job whose worker grows past "
                                            "this much memory [MB] is stopped with that reason, and a job whose "
                                            "parameters clearly need more is refused (422); 0 = no limit. "
                                            "Default: 80 % of the machine's memory split between the jobs that "
                                            "run at once ('workers'; a Celery worker: its --concurrency).")
    api_keys: str = Field("", description="Comma-separated API keys; empty = no authentication.")
    open_paths: str = Field("/healthz", max_length=2000, description="Comma-separated paths that need no API "
                            "key when keys are set (a path opens itself and everything below it, e.g. "
                            "'/healthz,/viewer,/docs,/openapi.json'); every other path needs a key.")
    max_header_bytes: int = Field(64 * 1024, ge=4096, le=16 * 1024**2, description="Largest request head "
                                  "(request line and headers) `lidarmap serve` reads; past it: 431.")

    @model_validator(mode="after")
    def _heartbeat_below_loss(self) -> Settings:
        if self.worker_lost_s < 2 * self.heartbeat_s:
            raise ValueError(f"worker_lost_s ({self.worker_lost_s}) must be at least twice heartbeat_s "
                             f"({self.heartbeat_s}), or live jobs would be failed as lost")
        return self

    def job_memory_limit(self, jobs_at_once: int | None = None) -> int:
        """The per-job memory limit [MB] (0 = none): the setting, or the machine's share per job."""
        if self.job_memory_limit_mb is not None:
            return self.job_memory_limit_mb
        from service.memory_watchdog import default_limit_mb

        return default_limit_mb(jobs_at_once or self.workers)

    def open_path_list(self) -> list[str]:
        """The paths open without a key (blank entries dropped, no trailing slash)."""
        return [path.strip().rstrip("/") or "/" for path in self.open_paths.split(",") if path.strip()]

    def api_key_list(self) -> list[str]:
        """The configured keys (blank entries dropped)."""
        return [key.strip() for key in self.api_keys.split(",") if key.strip()]


def get_settings() -> Settings:
    """Settings read now from the environment (never at import time)."""
    return Settings()
