"""``animation.gif``: the map being built, one frame per snapshot (taken every N processed scans by
the engine) plus the final map, with the trajectory so far in red. Every frame has the final map's
framing: the canvas covers the final map's known cells (what the map shows), and a snapshot is cut
to it. The engine draws the snapshots as the final map is drawn (its poses, its rays) whenever it
re-renders the final map (:func:`slam_engine.pipeline.filter_result`). A saved map draws the same
frames from its bundle when asked for later (:func:`write_bundle_animation`, ``lidarmap animate``).

The run keeps its snapshots small (:meth:`~slam_engine.model.result.MapSnapshot.reduced`: maps pooled to
at most 800 cells a side, what a frame shows anyway), so frames are drawn from small maps; frames
are palette images with a fixed palette, so the GIF encoder has no colours to quantize.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from slam_engine.config import GridConfig
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.result import MapSnapshot, OccupancyGrid, Trajectory
from slam_engine.products.files import atomic_path
from slam_engine.products.rendering import TRAJECTORY_RGB, UNKNOWN_GRAY, occupancy_image

FRAME_DURATION_MS = 120
LAST_FRAME_DURATION_MS = 2000
MAX_SIDE_PX = 800
ANIMATION_FRAMES = 40  # frames aimed at when a run sets no snapshot interval (`lidarmap run`, bench)


def snapshot_interval(scans: int) -> int:
    """``snapshot_every_scans`` that gives about :data:`ANIMATION_FRAMES` frames for a log of ``scans``."""
    return max(1, scans // ANIMATION_FRAMES)


# Frames are palette images: indices 0..254 are greys from black to white, 255 the trajectory red.
# A fixed palette spares the GIF encoder quantizing every RGB frame.
_TRAJECTORY_INDEX = 255
_PALETTE = [round(i * 255 / 254) for i in range(255) for _ in range(3)] + list(TRAJECTORY_RGB)
_GRAY_TO_INDEX = np.rint(np.arange(256) * 254 / 255).astype(np.uint8)


def animation_frames(snapshots: list[MapSnapshot], final_grid: OccupancyGrid, final_trajectory: Trajectory,
                     max_side_px: int = MAX_SIDE_PX) -> Iterator[Image.Image]:
    """Palette frames, drawn as they are asked for: each snapshot, then the final map; canvases share
    the final map's framing (:func:`map_extent`) and scale (the final grid's resolution times the
    smallest whole factor that brings the longer side to <= ``max_side_px``)."""
    res = final_grid.resolution_m
    left, bottom, right, top = map_extent(final_grid)
    shrink = max(1, math.ceil(max((right - left) / res, (top - bottom) / res) / max_side_px - 1e-9))
    pixel_m = res * shrink
    width, height = max(1, round((right - left) / pixel_m)), max(1, round((top - bottom) / pixel_m))
    final = MapSnapshot(scan_index=-1, t_s=0.0, grid=final_grid, trajectory=final_trajectory)
    for snapshot in [*snapshots, final]:
        grid = snapshot.grid.pooled(max(1, math.floor(pixel_m / snapshot.grid.resolution_m + 1e-9)))
        image = occupancy_image(grid)
        scale = grid.resolution_m / pixel_m
        if abs(scale - 1.0) > 1e-9:
            image = image.resize((max(1, round(image.width * scale)), max(1, round(image.height * scale))),
                                 Image.Resampling.NEAREST)
        canvas = np.full((height, width), _GRAY_TO_INDEX[UNKNOWN_GRAY], np.uint8)
        col0 = round((grid.origin_x_m - left) / pixel_m)
        row0 = round((top - (grid.origin_y_m + grid.shape[0] * grid.resolution_m)) / pixel_m)
        pixels = _GRAY_TO_INDEX[np.asarray(image)]
        # pooling pads a grid up to whole blocks, so it may reach past the canvas: paste the overlap
        r0, c0 = max(row0, 0), max(col0, 0)
        rows = min(pixels.shape[0] - (r0 - row0), height - r0)
        cols = min(pixels.shape[1] - (c0 - col0), width - c0)
        if rows > 0 and cols > 0:
            canvas[r0:r0 + rows, c0:c0 + cols] = pixels[r0 - row0:r0 - row0 + rows, c0 - col0:c0 - col0 + cols]
        frame = Image.fromarray(canvas)
        frame.putpalette(_PALETTE)
        trajectory = snapshot.trajectory
        if len(trajectory) > 1:
            points = [((x - left) / pixel_m, (top - y) / pixel_m) for x, y in trajectory.poses[:, :2]]
            ImageDraw.Draw(frame).line(points, fill=_TRAJECTORY_INDEX, width=1)
        yield frame


def map_extent(grid: OccupancyGrid) -> tuple[float, float, float, float]:
    """(left, bottom, right, top) [m, map frame] of the grid's known cells (the whole grid when none is)."""
    known = grid.known()
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    h, w = grid.shape
    (iy0, iy1), (ix0, ix1) = ((rows[0], rows[-1] + 1), (cols[0], cols[-1] + 1)) if len(rows) else ((0, h), (0, w))
    res = grid.resolution_m
    return (grid.origin_x_m + ix0 * res, grid.origin_y_m + iy0 * res,
            grid.origin_x_m + ix1 * res, grid.origin_y_m + iy1 * res)


def write_animation_gif(snapshots: list[MapSnapshot], final_grid: OccupancyGrid, final_trajectory: Trajectory,
                        path: str | Path, max_side_px: int = MAX_SIDE_PX) -> Path:
    """Write the looping GIF (len(snapshots) + 1 frames; Pillow merges identical consecutive frames).
    Frames are drawn one at a time as Pillow takes them (it keeps its own copy of each until it writes)."""
    frames = animation_frames(snapshots, final_grid, final_trajectory, max_side_px)
    durations = [FRAME_DURATION_MS] * len(snapshots) + [LAST_FRAME_DURATION_MS]
    with atomic_path(path) as tmp:
        next(frames).save(tmp, format="GIF", save_all=True, append_images=frames, duration=durations, loop=0)
    return Path(path)


def bundle_snapshots(bundle: MapBundle, frames: int = ANIMATION_FRAMES
                     ) -> tuple[list[MapSnapshot], OccupancyGrid, Trajectory]:
    """A saved map's animation, as a run draws it: (``frames`` - 1 snapshots or fewer, the final map, the
    final trajectory). Snapshot n is the map of the bundle's first key frames (evenly many more each time) at
    their final poses, rendered with the run's grid settings (the bundle's config), in one pass over them
    (:func:`~slam_engine.backend.map_builder.render_with_frames`), with the trajectory of that key frame's
    drive up to its time; the final map and trajectory are the last drive's whole."""
    from slam_engine.backend.map_builder import render_with_frames  # numba kernels: imported when used

    key_frames = len(bundle)
    grid_config = GridConfig.model_validate({**bundle.config.get("grid", {}), "resolution_m": bundle.resolution_m})
    marks = sorted({int(n) for n in np.ceil(np.linspace(0, key_frames, max(1, frames) + 1)[1:-1]) if n > 0})
    grid, kept = render_with_frames(bundle.scans(), bundle.poses, bundle.origin_v, grid_config, marks)

    def driven(drive: int, until_s: float) -> Trajectory:
        mine = (bundle.trajectory_drive == drive) & (bundle.trajectory_t_s <= until_s)
        return Trajectory(bundle.trajectory_t_s[mine], bundle.trajectory[mine])

    snapshots = [MapSnapshot(n - 1, float(bundle.t_s[n - 1]), kept[n],
                             driven(int(bundle.drive[n - 1]), float(bundle.t_s[n - 1]))) for n in marks]
    last = int(bundle.drive[-1]) if key_frames else 0
    return snapshots, grid, driven(last, math.inf)


def write_bundle_animation(bundle: MapBundle, path: str | Path, frames: int = ANIMATION_FRAMES,
                           max_side_px: int = MAX_SIDE_PX) -> Path:
    """Write a saved map's ``animation.gif`` (:func:`bundle_snapshots`, :func:`write_animation_gif`)."""
    snapshots, grid, trajectory = bundle_snapshots(bundle, frames)
    return write_animation_gif(snapshots, grid, trajectory, path, max_side_px)
