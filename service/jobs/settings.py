"""A job's settings as the service validates and stores them: the engine's own SlamConfig (its bounds,
its defaults), with JobCreate's shortcut fields laid over it.

Stored job config: ``{"slam": <the whole SlamConfig>, "live", "idle_timeout_s", and the shortcut fields
with their effective values}``; :func:`engine_config` reads it back (rows stored before ``slam`` existed
hold the shortcuts only)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from api_schemas.jobs import JobCreate
from slam_engine.config import (
    SHORTCUTS,
    SlamConfig,
    merge_settings,
    shortcut_overrides,
    shortcut_values,
    validate_config,
)

JOB_SNAPSHOT_EVERY_SCANS = 50  # a job shows its map growing unless told otherwise (the engine's default: 0)

class JobSettings(JobCreate):
    """JobCreate with ``slam`` validated as a SlamConfig (the OpenAPI schema shows its bounds)."""

    slam: SlamConfig = Field(default_factory=SlamConfig, description="Engine settings, nested by section, "  # type: ignore[assignment]
                             "any subset (the rest keep their defaults); the shortcut fields override them.")


def resolve(settings: JobSettings) -> SlamConfig:
    """The engine configuration of a job: ``slam``, then the shortcuts given; validated with the engine's
    bounds (ConfigError -> 422 naming the setting)."""
    merged = settings.slam.model_dump()
    if "snapshot_every_scans" not in settings.slam.model_fields_set:
        merged["snapshot_every_scans"] = JOB_SNAPSHOT_EVERY_SCANS
    merged = merge_settings(merged, shortcut_overrides({name: getattr(settings, name) for name in SHORTCUTS}))
    return validate_config(merged, "job settings")


def stored_config(settings: JobSettings, config: SlamConfig) -> dict[str, Any]:
    """What the store keeps as the job's config."""
    return {**shortcut_values(config), "live": settings.live, "idle_timeout_s": settings.idle_timeout_s,
            "mode": settings.mode.value, "map_job_id": settings.map_job_id, "merge_job_id": settings.merge_job_id,
            "slam": config.model_dump(mode="json")}


def engine_config(job_config: dict[str, Any]) -> SlamConfig:
    """The SlamConfig a stored job runs with."""
    if "slam" in job_config:
        return validate_config(job_config["slam"], "job settings")
    legacy = {name: job_config.get(name) for name in SHORTCUTS}
    return validate_config(shortcut_overrides(legacy), "job settings")
