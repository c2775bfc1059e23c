"""Service settings from the environment (prefix ``LIDARMAP_``), validated on creation."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Embedded defaults: SQLite, local disk and local worker processes, no external server."""

    model_config = SettingsConfigDict(env_prefix="LIDARMAP_", extra="ignore")

    data_dir: Path = Field(Path("lidarmap-data"), description="Where the job store, uploads and "
                           "artifacts live.")
    workers: int = Field(2, ge=1, le=64, description="Local SLAM worker processes.")
    max_upload_bytes: int = Field(2 * 1024**3, ge=1024, le=1024**4, description="Largest accepted upload.")
    api_keys: str = Field("", description="Comma-separated API keys; empty = no authentication.")


def get_settings() -> Settings:
    """Settings read now from the environment (never at import time)."""
    return Settings()
