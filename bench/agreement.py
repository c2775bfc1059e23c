"""Map numbers for logs without ground truth (the map PNG comes from slam_engine.products.rendering).

- ``wall_thickness_m``: 2 x occupied area / occupied-free boundary length of the final grid. A
  straight one-cell wall scores about one cell; blurred or doubled walls score more.
- ``occupied_with_neighbour``: fraction of occupied cells with at least one occupied 8-neighbour
  (isolated specks lower it).
- ``half_agreement``: scan endpoints of the first and the second half of the log, placed with the
  estimated trajectory; of the hit cells of one half that lie within ``window_m`` of the other
  half's hits (the part both halves saw), the fraction within one cell (``half_mean_offset_m``: their
  mean distance). Walls seen twice coincide when the trajectory is consistent.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from slam_engine.model.drive_log import DriveLog
from slam_engine.model.result import OccupancyGrid, Trajectory

OCCUPIED_PROBABILITY = 0.65
# The half agreement uses its own fixed cells so that runs with different grids compare.
AGREEMENT_RESOLUTION_M = 0.05
AGREEMENT_WINDOW_M = 0.5


def scan_endpoints_world(log: DriveLog, trajectory: Trajectory, max_range_m: float) -> np.ndarray:
    """(N_scans, N_beams, 2) map-frame endpoints [m] of every scan placed at the trajectory pose
    nearest in time, each scan's beams at its own angles; NaN for no-return beams and beams beyond
    ``max_range_m``."""
    lidar, scans = log.lidar, log.scans
    if lidar is None or scans is None:
        raise ValueError("the log has no LiDAR scans")
    ranges = np.asarray(scans.ranges_m, dtype=np.float64)
    valid = np.isfinite(ranges) & (ranges >= lidar.range_min_m) & (ranges <= min(lidar.range_max_m, max_range_m))
    ranges = np.where(valid, ranges, 0.0)  # no-return beams become NaN below, without inf * 0 warnings
    angles = lidar.beam_angles_rad
    if scans.angle_offset_rad is not None:  # each scan's own start angle (interlaced lasers)
        angles = angles[None, :] + np.asarray(scans.angle_offset_rad, dtype=np.float64)[:, None]
    T = np.asarray(lidar.T_vehicle_from_lidar, dtype=np.float64)
    # Beam endpoints in the vehicle frame (the 2-D part of T_vehicle_from_lidar).
    x_lidar, y_lidar = ranges * np.cos(angles), ranges * np.sin(angles)
    x_vehicle = T[0, 0] * x_lidar + T[0, 1] * y_lidar + T[0, 3]
    y_vehicle = T[1, 0] * x_lidar + T[1, 1] * y_lidar + T[1, 3]
    index = np.clip(np.searchsorted(trajectory.t_s, scans.t_s), 0, len(trajectory) - 1)
    previous = np.clip(index - 1, 0, len(trajectory) - 1)
    closer = np.abs(trajectory.t_s[previous] - scans.t_s) < np.abs(trajectory.t_s[index] - scans.t_s)
    pose = trajectory.poses[np.where(closer, previous, index)]
    cos_t, sin_t = np.cos(pose[:, 2:3]), np.sin(pose[:, 2:3])
    x_world = pose[:, 0:1] + cos_t * x_vehicle - sin_t * y_vehicle
    y_world = pose[:, 1:2] + sin_t * x_vehicle + cos_t * y_vehicle
    points = np.stack([x_world, y_world], axis=-1)
    points[~valid] = np.nan
    return points


# p > OCCUPIED_PROBABILITY, as log-odds: no exp over every cell of a large map
_OCCUPIED_LOG_ODDS = float(np.log(OCCUPIED_PROBABILITY / (1.0 - OCCUPIED_PROBABILITY)))


def _occupied(grid: OccupancyGrid) -> np.ndarray:
    """Occupied cells (probability above ``OCCUPIED_PROBABILITY``), cropped to the box around them
    with a free margin of one cell (what the neighbour and edge counts below read: the rest of a
    large map is empty)."""
    occupied = grid.log_odds > _OCCUPIED_LOG_ODDS
    rows, cols = np.flatnonzero(occupied.any(axis=1)), np.flatnonzero(occupied.any(axis=0))
    if len(rows) == 0:
        return np.zeros((0, 0), bool)
    return np.pad(occupied[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1], 1)


def wall_thickness_m(grid: OccupancyGrid) -> float:
    """2 x occupied area / boundary length [m] (NaN for a map without occupied cells)."""
    occupied = _occupied(grid)
    area = int(occupied.sum())
    if area == 0:
        return float("nan")
    edges = int(np.count_nonzero(occupied[1:, :] != occupied[:-1, :])
                + np.count_nonzero(occupied[:, 1:] != occupied[:, :-1]))
    return 2.0 * area / edges * grid.resolution_m


def occupied_with_neighbour(grid: OccupancyGrid) -> float:
    """Fraction of occupied cells with at least one occupied 8-neighbour (NaN when none occupied)."""
    occupied = _occupied(grid)
    if not occupied.any():
        return float("nan")
    neighbours = ndimage.convolve(occupied.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - occupied
    return float(np.mean(neighbours[occupied] > 0))


def _hit_cells(points: np.ndarray, origin: np.ndarray, resolution_m: float, min_hits: int) -> np.ndarray:
    """(K, 2) integer (x, y) cells, counted from ``origin`` [m], that hold at least ``min_hits`` of
    ``points`` (N, 2) [m]; NaN points are dropped."""
    points = points[np.isfinite(points[:, 0])]
    cells = np.floor((points - origin) / resolution_m).astype(np.int64)
    if len(cells) == 0:
        return np.zeros((0, 2), np.int64)
    # one integer per cell (cells are >= 0 from the origin), counted by sorting: no dense grid
    rows = int(cells[:, 1].max()) + 1
    keys, counts = np.unique(cells[:, 0] * rows + cells[:, 1], return_counts=True)
    keys = keys[counts >= min_hits]
    return np.column_stack([keys // rows, keys % rows])


def half_agreement(endpoints: np.ndarray, resolution_m: float = AGREEMENT_RESOLUTION_M,
                   window_m: float = AGREEMENT_WINDOW_M, min_hits: int = 2) -> dict:
    """Agreement of the walls seen in the first and the second half of the scans (module docstring).

    ``endpoints`` (N_scans, N_beams, 2) as from :func:`scan_endpoints_world`. Each hit cell's distance
    to the other half's nearest hit cell is the Euclidean distance between cell indices (what a
    distance transform of the other half's hit grid gives), found with a k-d tree over the hit cells
    alone: a long drive's dense grid (tens of millions of cells) took seconds."""
    half = endpoints.shape[0] // 2
    first, second = endpoints[:half].reshape(-1, 2), endpoints[half:].reshape(-1, 2)
    every = endpoints.reshape(-1, 2)
    every = every[np.isfinite(every[:, 0])]
    if half == 0 or every.shape[0] == 0:
        return {"half_agreement": float("nan"), "half_mean_offset_m": float("nan"), "half_overlap_cells": 0}
    # imported here: the bench's worker imports this module before the run it measures (about 6 MB)
    from scipy.spatial import cKDTree

    origin = every.min(axis=0) - 2 * resolution_m
    hits = [_hit_cells(part, origin, resolution_m, min_hits) for part in (first, second)]
    reach_cells = window_m / resolution_m + 1.0  # farther neighbours are outside the window anyway
    offsets = []
    for mine, theirs in ((hits[0], hits[1]), (hits[1], hits[0])):
        if len(theirs) == 0 or len(mine) == 0:
            continue
        cells_away, _ = cKDTree(theirs).query(mine, distance_upper_bound=reach_cells)
        distance = cells_away * resolution_m
        offsets.append(distance[distance <= window_m])
    all_offsets = np.concatenate(offsets) if offsets else np.zeros(0)
    if all_offsets.size == 0:
        return {"half_agreement": float("nan"), "half_mean_offset_m": float("nan"), "half_overlap_cells": 0}
    return {"half_agreement": float(np.mean(all_offsets <= resolution_m * 1.5)),
            "half_mean_offset_m": float(np.mean(all_offsets)), "half_overlap_cells": int(all_offsets.size)}


def map_quality(grid: OccupancyGrid, log: DriveLog | None = None, trajectory: Trajectory | None = None,
                max_range_m: float = 30.0) -> dict:
    """All map numbers above; the half agreement only when the log has scans and a LiDAR model."""
    numbers = {"wall_thickness_m": wall_thickness_m(grid), "occupied_with_neighbour": occupied_with_neighbour(grid),
               "occupied_cells": int(_occupied(grid).sum())}
    if log is not None and trajectory is not None and log.scans is not None and log.lidar is not None \
            and len(log.scans) and len(trajectory):
        numbers.update(half_agreement(scan_endpoints_world(log, trajectory, max_range_m)))
    return numbers
