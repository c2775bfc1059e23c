"""The occupancy grid re-rendered from the key frames' scans at their optimised poses."""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence

import numpy as np

from slam_engine.config import GridConfig
from slam_engine.frontend.grid import ParticleGrids
from slam_engine.frontend.lidar_points import ProjectedScan
from slam_engine.frontend.raycast import insert_scan
from slam_engine.model.result import SNAPSHOT_MAX_SIDE_CELLS, MapSnapshot, OccupancyGrid, Trajectory


def render_occupancy(scans: Sequence[ProjectedScan], poses: np.ndarray, origin_v: np.ndarray, grid: GridConfig,
                     frames_after: Collection[int] = (),
                     on_frame: Callable[[int, OccupancyGrid], None] | None = None,
                     frame_max_side_cells: int | None = None) -> OccupancyGrid:
    """Log-odds grid of every scan in ``scans`` inserted at its vehicle pose ``poses`` (K, 3, world
    frame); ``origin_v`` (2,) is the LiDAR's position in the vehicle frame [m]. ``on_frame(n, grid)``
    is handed the map of the first ``n`` scans for each ``n`` in ``frames_after`` (the map being
    built, for the animation), in the same pass; with ``frame_max_side_cells``, pooled to at most that
    many cells a side (:meth:`OccupancyGrid.pooled`, built from the tiles without the full-resolution
    map: on infinite-corridor-rough 1.4 s less than pooling each full map)."""
    grids = ParticleGrids(1, grid.resolution_m)
    for k, (scan, pose) in enumerate(zip(scans, np.asarray(poses, np.float64), strict=True)):
        insert_scan(grids, pose[None, :], origin_v, scan.ends_v, scan.is_hit, grid.log_odds_hit, grid.log_odds_miss,
                    grid.log_odds_min, grid.log_odds_max, scan.free_from_m)
        if on_frame is not None and k + 1 in frames_after:
            on_frame(k + 1, grids.occupancy_grid(0) if frame_max_side_cells is None
                     else grids.occupancy_grid_within(0, frame_max_side_cells))
    return grids.occupancy_grid(0)


def render_with_frames(scans: Sequence[ProjectedScan], poses: np.ndarray, origin_v: np.ndarray, grid: GridConfig,
                       frames_after: Collection[int]) -> tuple[OccupancyGrid, dict[int, OccupancyGrid]]:
    """:func:`render_occupancy` and, in the same pass, the map of the first n scans for each n in
    ``frames_after`` at an animation frame's size, kept compressed as a run keeps its snapshots
    (:meth:`~slam_engine.model.result.MapSnapshot.reduced`): the animation's frames at the final poses."""
    frames: dict[int, OccupancyGrid] = {}
    nowhere = Trajectory(np.zeros(0), np.zeros((0, 3)))

    def keep(n: int, partial: OccupancyGrid) -> None:
        frames[n] = MapSnapshot(-1, 0.0, partial, nowhere).reduced().grid

    final = render_occupancy(scans, poses, origin_v, grid, frames_after=frames_after, on_frame=keep,
                             frame_max_side_cells=SNAPSHOT_MAX_SIDE_CELLS)
    return final, frames
