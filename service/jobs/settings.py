"""A job's settings as the service validates and stores them: the engine's own SlamConfig (its bounds,
its defaults), with JobCreate's shortcut fields laid over it.

Stored job config: ``{"slam": <the whole SlamConfig>, "live", "idle_timeout_s", and the shortcut fields
with their effective values}``; :func:`engine_config` reads it back (rows stored before ``slam`` existed
hold the shortcuts only)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from api_schemas.jobs import JobCreate
from slam_engine.config import SlamConfig, merge_settings, validate_config

JOB_SNAPSHOT_EVERY_SCANS = 50  # a job shows its map growing unless told otherwise (the engine's default: 0)

# JobCreate shortcut -> its place in SlamConfig
SHORTCUTS: dict[str, tuple[str, ...]] = {
    "particles": ("particles",),
    "seed": ("seed",),
    "resolution_m": ("grid", "resolution_m"),
    "max_range_m": ("grid", "max_range_m"),
    "linear_update_m": ("scheduling", "linear_update_m"),
    "angular_update_rad": ("scheduling", "angular_update_rad"),
    "snapshot_every_scans": ("snapshot_every_scans",),
}


class JobSettings(JobCreate):
    """JobCreate with ``slam`` validated as a SlamConfig (the OpenAPI schema shows its bounds)."""

    slam: SlamConfig = Field(default_factory=SlamConfig, description="Engine settings, nested by section, "  # type: ignore[assignment]
                             "any subset (the rest keep their defaults); the shortcut fields override them.")


def _nested(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    return {path[0]: value} if len(path) == 1 else {path[0]: _nested(path[1:], value)}


def resolve(settings: JobSettings) -> SlamConfig:
    """The engine configuration of a job: ``slam``, then the shortcuts given; validated with the engine's
    bounds (ConfigError -> 422 naming the setting)."""
    merged = settings.slam.model_dump()
    if "snapshot_every_scans" not in settings.slam.model_fields_set:
        merged["snapshot_every_scans"] = JOB_SNAPSHOT_EVERY_SCANS
    for name, path in SHORTCUTS.items():
        value = getattr(settings, name)
        if value is not None:
            merged = merge_settings(merged, _nested(path, value))
    return validate_config(merged, "job settings")


def stored_config(settings: JobSettings, config: SlamConfig) -> dict[str, Any]:
    """What the store keeps as the job's config."""
    shortcuts = {}
    for name, path in SHORTCUTS.items():
        value: Any = config
        for key in path:
            value = getattr(value, key)
        shortcuts[name] = value
    return {**shortcuts, "live": settings.live, "idle_timeout_s": settings.idle_timeout_s,
            "slam": config.model_dump(mode="json")}


def engine_config(job_config: dict[str, Any]) -> SlamConfig:
    """The SlamConfig a stored job runs with."""
    if "slam" in job_config:
        return validate_config(job_config["slam"], "job settings")
    legacy = {name: job_config[name] for name in SHORTCUTS if job_config.get(name) is not None}
    settings: dict[str, Any] = {}
    for name, value in legacy.items():
        settings = merge_settings(settings, _nested(SHORTCUTS[name], value))
    return validate_config(settings, "job settings")
