"""The engine's output: trajectories, the occupancy grid, the texture map and per-scan statistics.

Map frame: the world frame of the run, x/y in metres, theta in radians, origin at the first pose.
Grid layout: ``log_odds[iy, ix]``; cell (ix, iy) covers
``[origin_x_m + ix * resolution_m, +resolution_m) x [origin_y_m + iy * resolution_m, +resolution_m)``,
so row index grows with y (north up means flipping rows for an image).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from slam_engine.config import SlamConfig
    from slam_engine.model.map_bundle import MapBundle

SNAPSHOT_MAX_SIDE_CELLS = 800  # a kept snapshot's map is pooled to at most this (what an animation frame shows)
PREVIEW_MAX_SIDE_CELLS = 2048  # the newest snapshot's map (live previews) is pooled to at most about this


@dataclass
class Trajectory:
    """Timestamped SE(2) poses: ``t_s`` (N,) seconds, ``poses`` (N, 3) [x_m, y_m, theta_rad]."""

    t_s: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def until(self, t_s: float) -> Trajectory:
        """The poses at or before ``t_s``."""
        keep = self.t_s <= t_s
        return Trajectory(t_s=self.t_s[keep], poses=self.poses[keep])


@dataclass
class OccupancyGrid:
    """A log-odds occupancy grid with its placement in the map frame."""

    log_odds: np.ndarray
    resolution_m: float
    origin_x_m: float
    origin_y_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.log_odds.shape  # (rows = y cells, cols = x cells)

    def probability(self) -> np.ndarray:
        """(H, W) occupancy probability in [0, 1]; 0.5 where unknown."""
        return 1.0 / (1.0 + np.exp(-self.log_odds.astype(np.float64)))

    def known(self) -> np.ndarray:
        """(H, W) bool: cells that at least one beam observed."""
        return self.log_odds != 0.0

    def world_to_cell(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer cell indices (ix, iy) of map-frame points [m]."""
        ix = np.floor((np.asarray(x_m) - self.origin_x_m) / self.resolution_m).astype(np.int64)
        iy = np.floor((np.asarray(y_m) - self.origin_y_m) / self.resolution_m).astype(np.int64)
        return ix, iy

    def cell_to_world(self, ix: np.ndarray, iy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame coordinates [m] of cell centres."""
        x = self.origin_x_m + (np.asarray(ix) + 0.5) * self.resolution_m
        y = self.origin_y_m + (np.asarray(iy) + 0.5) * self.resolution_m
        return x, y

    def pooled(self, factor: int) -> OccupancyGrid:
        """This grid with cells ``factor`` times larger (same origin): a block's log-odds is the
        largest among its known cells (obstacles stay visible), 0 (unknown) where none is known."""
        if factor <= 1:
            return self
        from slam_engine.frontend.map_pooling import pool_known_max  # numba kernel; imported when used

        out = pool_known_max(np.ascontiguousarray(self.log_odds, np.float32), int(factor))
        return OccupancyGrid(out, self.resolution_m * factor, self.origin_x_m, self.origin_y_m)


class CompactGrid(OccupancyGrid):
    """An :class:`OccupancyGrid` kept zlib-compressed (its float32 values, losslessly: maps are mostly
    large flat areas, a tenth of the size or less); ``log_odds`` is decompressed on each access, a
    read-only array. What a run keeps of its older snapshots."""

    def __init__(self, grid: OccupancyGrid):
        values = np.ascontiguousarray(grid.log_odds, np.float32)
        self._shape: tuple[int, int] = (int(values.shape[0]), int(values.shape[1]))
        self._packed = zlib.compress(values.tobytes(), 1)
        self.resolution_m = grid.resolution_m
        self.origin_x_m = grid.origin_x_m
        self.origin_y_m = grid.origin_y_m

    @property
    def log_odds(self) -> np.ndarray:  # type: ignore[override]  # read-only here
        return np.frombuffer(zlib.decompress(self._packed), np.float32).reshape(self._shape)

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    @property
    def packed_bytes(self) -> int:
        return len(self._packed)


@dataclass
class TextureMap:
    """Ground colours on the occupancy grid's geometry: ``colors`` (H, W, 3) uint8 RGB, or (H, W)
    for grayscale cameras; ``counts`` (H, W) observations per cell (0 = never seen)."""

    colors: np.ndarray
    counts: np.ndarray
    resolution_m: float
    origin_x_m: float
    origin_y_m: float


@dataclass
class ScanStats:
    """Per processed scan: time [s], effective sample size, resampled?, best match score,
    whether the scan matcher's correction was used, the step's wall time [s], and the number of
    particles after it (empty where not recorded)."""

    t_s: np.ndarray
    n_eff: np.ndarray
    resampled: np.ndarray
    match_score: np.ndarray
    matched: np.ndarray
    step_time_s: np.ndarray
    particles: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


@dataclass
class MapSnapshot:
    """The best particle's map part-way through a run (for animations and live previews)."""

    scan_index: int
    t_s: float
    grid: OccupancyGrid
    trajectory: Trajectory

    def reduced(self, max_side_cells: int = SNAPSHOT_MAX_SIDE_CELLS) -> MapSnapshot:
        """This snapshot with its map pooled (:meth:`OccupancyGrid.pooled`) to at most
        ``max_side_cells`` cells on the longer side and kept compressed (:class:`CompactGrid`);
        itself when that already."""
        factor = math.ceil(max(self.grid.shape) / max_side_cells)
        if factor <= 1 and isinstance(self.grid, CompactGrid):
            return self
        return MapSnapshot(self.scan_index, self.t_s, CompactGrid(self.grid.pooled(factor)), self.trajectory)


def preview_pool_factor(side_cells: int, max_side_cells: int = PREVIEW_MAX_SIDE_CELLS) -> int:
    """The pool factor of the newest snapshot's map, whose full-resolution map is ``side_cells`` on
    its longer side: the smallest that brings it to ``max_side_cells`` among the divisors of the
    factor :meth:`MapSnapshot.reduced` applies to the full map, so that reducing the pooled map later
    gives exactly the reduced full map (pooling by f, then by F / f, is pooling by F)."""
    final = max(1, math.ceil(side_cells / SNAPSHOT_MAX_SIDE_CELLS))
    for factor in range(1, final + 1):
        if final % factor == 0 and math.ceil(side_cells / factor) <= max_side_cells:
            return factor
    return final


@dataclass
class SlamResult:
    """Everything one run produces. ``trajectory`` and ``dead_reckoning`` have one pose per scan
    of the log (scans skipped by the motion thresholds get odometry-propagated poses)."""

    trajectory: Trajectory
    dead_reckoning: Trajectory
    grid: OccupancyGrid
    scan_stats: ScanStats
    config: SlamConfig
    texture: TextureMap | None = None
    snapshots: list[MapSnapshot] = field(default_factory=list)
    wall_time_s: float = 0.0
    peak_memory_bytes: int = 0
    warnings: list[str] = field(default_factory=list)
    input_summary: dict = field(default_factory=dict)
    bundle: MapBundle | None = None  # what a later drive needs to localise in, extend or merge this map
