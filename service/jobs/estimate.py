"""What a job costs in memory, judged before it runs: a request whose parameters' floor clearly
exceeds the job memory limit is refused up front (422 with the estimate) instead of growing until
the watchdog stops it; so is a drive whose estimate (:func:`check_drive_memory`: the engine's
model, which counts the map's cells over the drive's extent and the drive's scans) exceeds it - at
creation for an upload (from the figures its inspection stored), once the input is read for any job.

Floors, not forecasts (the real figure depends on the drive):

* particle maps: after resampling every particle writes its own copy of the tiles a scan
  touches, at least a half disc of ``max_range_m`` (a 180 degree scanner): int16 cells, plus a
  third for the coarser levels;
* animation frames: one dense float32 grid of the best map every ``snapshot_every_scans``
  processed scans, each at least that half disc, kept until the run ends.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError

if TYPE_CHECKING:  # the engine's model imports its kernels' module (numba): loaded when first used
    from slam_engine.evaluation.memory_estimate import DriveFigures

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


FIGURES_KEY = "memory_figures"  # where an upload's summary keeps its DriveFigures (not shown to users)


def stored_figures(summary: dict[str, Any]) -> DriveFigures | None:
    """The drive figures an upload's inspection stored in its summary (None for older uploads)."""
    from slam_engine.evaluation.memory_estimate import DriveFigures

    figures = summary.get(FIGURES_KEY)
    try:
        return None if figures is None else DriveFigures(**figures)
    except TypeError:
        return None


def drive_estimate(config: SlamConfig, figures: DriveFigures) -> dict[str, Any]:
    """The estimate of mapping a drive of these figures [bytes], with what it stems from."""
    from slam_engine.evaluation.memory_estimate import estimate_job_memory_bytes, map_extent_m

    width_m, height_m = map_extent_m(figures, config)
    return {"estimate_bytes": estimate_job_memory_bytes(config, figures), "map_width_m": round(width_m, 1),
            "map_height_m": round(height_m, 1), "beams": figures.beams}


def check_drive_memory(config: SlamConfig, figures: DriveFigures, scans: int | None, limit_mb: int,
                       prefix: str = "") -> None:
    """ConfigError (with the estimate and what it stems from) when mapping a drive of these figures is
    estimated to need more than ``limit_mb`` (0 = no limit); ``prefix`` opens its message."""
    if not limit_mb:
        return
    parts = drive_estimate(config, figures)
    if parts["estimate_bytes"] <= limit_mb * MB:
        return
    raise ConfigError(f"{prefix}mapping this drive is estimated to need {parts['estimate_bytes'] / MB:.0f} MB "
                      f"(a map of {parts['map_width_m']:.0f} m x {parts['map_height_m']:.0f} m at "
                      f"{config.grid.resolution_m:g} m cells, {scans or 0} scans), more than the job memory limit of "
                      f"{limit_mb} MB: use a coarser resolution_m, a shorter max_range_m or fewer particles, or map "
                      "the drive in parts")


class ExtentGuard:
    """Checks a running job's estimate again as its map grows: SLAM may bend a track far from its
    odometry (a drive whose scans barely constrain it: a 1 km line of one-beam scans became a map of
    598 m x 557 m), and the map's cells follow the corrected track, not the dead-reckoned box the
    first estimate used. :meth:`check` takes each snapshot of the run (its corrected track so far) and
    raises ConfigError once the box it spans makes the estimate pass the limit, long before the map
    itself is rendered."""

    def __init__(self, config: SlamConfig, figures: DriveFigures, scans: int | None, limit_mb: int):
        self.config, self.figures, self.scans, self.limit_mb = config, figures, scans, limit_mb
        self._checked: int | None = None

    def check(self, scan_index: int, track_xy: Any) -> None:
        """``track_xy``: (N, 2+) corrected poses so far [m], of the snapshot at ``scan_index`` (each
        snapshot is checked once)."""
        import dataclasses

        import numpy as np

        if scan_index == self._checked:
            return
        self._checked = scan_index
        poses = np.asarray(track_xy, dtype=np.float64)
        if not self.limit_mb or poses.ndim != 2 or len(poses) < 2:
            return
        width, height = (float(v) for v in np.ptp(poses[:, :2], axis=0))
        if width <= self.figures.track_width_m and height <= self.figures.track_height_m:
            return
        grown = dataclasses.replace(self.figures, track_width_m=max(width, self.figures.track_width_m),
                                    track_height_m=max(height, self.figures.track_height_m))
        check_drive_memory(self.config, grown, self.scans, self.limit_mb,
                           prefix=f"stopped: the corrected track spans {width:.0f} m x {height:.0f} m, beyond its "
                                  f"odometry's {self.figures.track_width_m:.0f} m x "
                                  f"{self.figures.track_height_m:.0f} m; ")
