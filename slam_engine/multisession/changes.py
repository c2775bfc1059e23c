"""What changed since the saved map: cells a new drive, placed in the map, sees otherwise.

The saved map's occupancy grid is pooled to ``changes.resolution_m`` cells. The new drive's scans,
thinned to poses ``key_spacing_m`` / ``key_spacing_rad`` apart, are cast into the same cells: for each
cell, how many scans ended a beam in it (``hits``) and how many passed through it (``passes``), each
scan counted once per cell. A cell is

- **added** where the saved map held it free, at least ``min_scans`` scans hit it and they are at least
  ``hit_share`` of the scans that observed it (a person walking past is hit by few, then seen through),
  and the saved map has no obstacle within ``tolerance_cells``;
- **removed** where the saved map held it occupied, at least ``min_scans`` scans passed through it, and
  none of the new drive's beams ended within ``tolerance_cells`` of it (a wall still standing is hit
  beside where it was, however a beam grazes it).

Changed regions smaller than ``min_region_cells`` are dropped. Only cells both the saved map and the new
drive observed are judged. Frames: the map frame of the saved map; poses ``[x_m, y_m, theta_rad]``,
scan end points (N, 2) [m] in the vehicle frame, ``origin_v`` the LiDAR's position in it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba as nb
import numpy as np

from slam_engine.config import ChangesConfig, SlamConfig
from slam_engine.model.poses import key_poses, place_points
from slam_engine.model.result import OccupancyGrid

if TYPE_CHECKING:
    from slam_engine.multisession.joining import JoinedMap
    from slam_engine.multisession.localization import DriveScans, LocalizationResult


@dataclass
class ChangeMap:
    """Cells (H, W) of ``resolution_m`` from ``origin_m`` (map frame, row = y): ``added`` and ``removed``
    (bool), ``observed`` (both the saved map and the new drive observed it), ``saved_occupied`` (the
    saved map's obstacles), and the new drive's evidence: ``hits`` and ``passes`` (scans per cell), from
    ``scans_used`` of its scans."""

    added: np.ndarray
    removed: np.ndarray
    observed: np.ndarray
    saved_occupied: np.ndarray
    hits: np.ndarray
    passes: np.ndarray
    resolution_m: float
    origin_m: np.ndarray
    scans_used: int
    wall_time_s: float = 0.0

    def regions(self, which: np.ndarray) -> int:
        from scipy import ndimage

        return int(ndimage.label(which, structure=np.ones((3, 3)))[1])

    def summary(self) -> dict:
        """run.json's ``changes``: areas [m^2] added, removed and observed, the share of the observed area
        that changed, and how many separate regions."""
        cell_m2 = self.resolution_m ** 2
        observed = int(self.observed.sum())
        changed = int(self.added.sum() + self.removed.sum())
        return {
            "resolution_m": self.resolution_m,
            "added_m2": round(float(self.added.sum()) * cell_m2, 3),
            "removed_m2": round(float(self.removed.sum()) * cell_m2, 3),
            "observed_m2": round(observed * cell_m2, 3),
            "changed_share": round(changed / observed, 5) if observed else 0.0,
            "added_regions": self.regions(self.added), "removed_regions": self.regions(self.removed),
            "scans_used": self.scans_used, "wall_time_s": round(self.wall_time_s, 3),
        }


def detect_changes(saved: OccupancyGrid, hits_v: Sequence[np.ndarray], poses: np.ndarray, origin_v: np.ndarray,
                   config: ChangesConfig | None = None) -> ChangeMap:
    """The change map of a drive whose scans ``hits_v`` (returned end points, vehicle frame) lie at
    ``poses`` (S, 3) in the map frame of the ``saved`` grid (see the module docstring)."""
    from scipy import ndimage

    config = ChangesConfig() if config is None else config
    started = time.perf_counter()
    factor = max(1, int(round(config.resolution_m / saved.resolution_m)))
    pooled = saved.pooled(factor)
    probability = pooled.probability()
    known = pooled.known()
    saved_occupied = known & (probability > 0.5)
    saved_free = known & (probability < 0.5)
    rows, cols = pooled.shape
    hits = np.zeros((rows, cols), np.int32)
    passes = np.zeros((rows, cols), np.int32)
    poses = np.asarray(poses, np.float64)
    keep = key_poses(poses, config.key_spacing_m, config.key_spacing_rad)
    origin = np.array([pooled.origin_x_m, pooled.origin_y_m])
    last_hit = np.full((rows, cols), -1, np.int32)
    last_pass = np.full((rows, cols), -1, np.int32)
    for n, k in enumerate(keep):
        if len(hits_v[k]) == 0:
            continue
        start = (place_points(poses[k], np.asarray(origin_v, np.float64)[None, :])[0] - origin) / pooled.resolution_m
        ends = (place_points(poses[k], np.asarray(hits_v[k], np.float64)) - origin) / pooled.resolution_m
        _count_rays(np.floor(start).astype(np.int64), np.floor(ends).astype(np.int64), n, hits, passes,
                    last_hit, last_pass)
    near = np.ones((2 * config.tolerance_cells + 1,) * 2, bool)
    near_saved_obstacle = ndimage.binary_dilation(saved_occupied, near) if config.tolerance_cells else saved_occupied
    new_hit = hits > 0
    near_new_hit = ndimage.binary_dilation(new_hit, near) if config.tolerance_cells else new_hit
    seen = hits + passes
    added = (saved_free & (hits >= config.min_scans) & (hits >= config.hit_share * seen) & ~near_saved_obstacle)
    removed = saved_occupied & (passes >= config.min_scans) & ~near_new_hit
    added, removed = _without_small(added, config.min_region_cells), _without_small(removed, config.min_region_cells)
    return ChangeMap(added, removed, known & (seen > 0), saved_occupied, hits, passes, pooled.resolution_m, origin,
                     len(keep), time.perf_counter() - started)


def localization_changes(saved: OccupancyGrid, drive: DriveScans, result: LocalizationResult,
                         config: ChangesConfig) -> ChangeMap | None:
    """The change map of a localised drive against the ``saved`` map's grid, from the scans that matched
    the map (those carried by the drive's own motion may lie off by more than a cell); None when
    ``config.enabled`` is off or the drive was refused."""
    if not config.enabled or not result.localised or result.trajectory is None:
        return None
    tracked = np.flatnonzero(result.tracked)
    return detect_changes(saved, [drive.hits[k] for k in tracked], result.trajectory.poses[tracked], drive.origin_v,
                          config)


def extension_changes(joined: JoinedMap, config: SlamConfig) -> tuple[ChangeMap, OccupancyGrid] | None:
    """The change map of the drive that extended a saved map, and the saved map's grid it was found
    against: the saved map's key frames rendered at their poses in the joint map, the new drive's key
    frames cast into it. None when ``changes.enabled`` is off or the drive was not placed."""
    from slam_engine.backend.map_builder import render_occupancy

    if not config.changes.enabled or not joined.connected:
        return None
    bundle = joined.bundle
    new = np.isin(bundle.drive, joined.part_drives)
    before = np.flatnonzero(~new & ~np.isin(bundle.drive, bundle.sensors.get("disconnected_drives", [])))
    if len(before) == 0 or not new.any():
        return None
    grid_config = config.grid.model_copy(update={"resolution_m": bundle.resolution_m})
    saved = render_occupancy([bundle.scan(int(k)) for k in before], bundle.poses[before], bundle.origin_v,
                             grid_config)
    frames = np.flatnonzero(new)
    changes = detect_changes(saved, [bundle.hits(int(k)) for k in frames], bundle.poses[frames], bundle.origin_v,
                             config.changes)
    return changes, saved


def _without_small(mask: np.ndarray, min_cells: int) -> np.ndarray:
    """``mask`` without its 8-connected regions of fewer than ``min_cells`` cells."""
    if min_cells <= 1 or not mask.any():
        return mask
    from scipy import ndimage

    labels, count = ndimage.label(mask, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    big = sizes >= min_cells
    big[0] = False
    return big[labels]


@nb.njit(cache=True, nogil=True)
def _count_rays(start, ends, scan, hits, passes, last_hit, last_pass):
    """One scan's beams from cell ``start`` (2,) to cells ``ends`` (N, 2) [ix, iy], walked by Bresenham:
    each cell a beam crosses counts once in ``passes``, each end cell once in ``hits`` (``last_*`` hold
    the last scan counted per cell); cells outside the grid are skipped."""
    rows, cols = hits.shape
    x0, y0 = start[0], start[1]
    for b in range(ends.shape[0]):
        x1, y1 = ends[b, 0], ends[b, 1]
        dx, dy = abs(x1 - x0), -abs(y1 - y0)
        sx = 1 if x0 < x1 else -1
        sy = 1 if y0 < y1 else -1
        err = dx + dy
        x, y = x0, y0
        while x != x1 or y != y1:
            if 0 <= x < cols and 0 <= y < rows and last_pass[y, x] != scan:
                last_pass[y, x] = scan
                passes[y, x] += 1
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x += sx
            if e2 <= dx:
                err += dx
                y += sy
        if 0 <= x1 < cols and 0 <= y1 < rows and last_hit[y1, x1] != scan:
            last_hit[y1, x1] = scan
            hits[y1, x1] += 1
