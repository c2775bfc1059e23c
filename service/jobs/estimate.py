"""What a job's parameters cost in memory at least, judged before it runs: a request whose floor
clearly exceeds the job memory limit is refused up front (422 with the estimate) instead of
growing until the watchdog stops it.

Floors, not forecasts (the real figure depends on the drive):

* particle maps: after resampling every particle writes its own copy of the tiles a scan
  touches, at least a half disc of ``max_range_m`` (a 180 degree scanner): int16 cells, plus a
  third for the coarser levels;
* animation frames: one dense float32 grid of the best map every ``snapshot_every_scans``
  processed scans, each at least that half disc, kept until the run ends.
"""

from __future__ import annotations

import math

from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError

MB = 1024 * 1024
MAP_CELL_BYTES = 2 * 4 / 3  # int16 level 0 plus the coarser levels
FRAME_CELL_BYTES = 4  # float32


def scan_cells(config: SlamConfig) -> float:
    """Cells of a half disc of ``max_range_m`` at ``resolution_m``."""
    return math.pi * (config.grid.max_range_m / config.grid.resolution_m) ** 2 / 2


def estimate_bytes(config: SlamConfig, scans: int | None) -> dict[str, int]:
    """Floors [bytes] of the particle maps and of the animation frames (0 when ``scans`` is unknown)."""
    cells = scan_cells(config)
    every = config.snapshot_every_scans
    frames = scans // every if (every and scans) else 0
    return {"particle_maps_bytes": int(config.particles * cells * MAP_CELL_BYTES),
            "animation_frames_bytes": int(frames * cells * FRAME_CELL_BYTES)}


def check_job_memory(config: SlamConfig, scans: int | None, limit_mb: int) -> None:
    """ConfigError (with the estimate) when the floor of a job's memory exceeds ``limit_mb`` (0 = none)."""
    if not limit_mb:
        return
    parts = estimate_bytes(config, scans)
    total = sum(parts.values())
    if total <= limit_mb * MB:
        return
    advice = "fewer particles, a coarser resolution_m or a shorter max_range_m"
    if parts["animation_frames_bytes"] > parts["particle_maps_bytes"]:
        advice = "a larger snapshot_every_scans (or 0), a coarser resolution_m or a shorter max_range_m"
    raise ConfigError(f"this job needs at least {total / MB:.0f} MB ({parts['particle_maps_bytes'] / MB:.0f} MB of "
                      f"particle maps, {parts['animation_frames_bytes'] / MB:.0f} MB of animation frames over "
                      f"{scans or 0} scans), more than the job memory limit of {limit_mb} MB: use {advice}")
