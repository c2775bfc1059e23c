"""``animation.gif``: the map being built, one frame per snapshot (taken every N scans by the engine)
plus the final map, all on one canvas covering every snapshot, with the trajectory so far in red."""

from __future__ import annotations

import math
from pathlib import Path

from PIL import Image, ImageDraw

from slam_engine.products.files import atomic_path
from slam_engine.products.rendering import TRAJECTORY_RGB, UNKNOWN_GRAY, occupancy_image
from slam_engine.result import MapSnapshot, OccupancyGrid, Trajectory

FRAME_DURATION_MS = 120
LAST_FRAME_DURATION_MS = 2000
MAX_SIDE_PX = 800


def animation_frames(snapshots: list[MapSnapshot], final_grid: OccupancyGrid, final_trajectory: Trajectory,
                     max_side_px: int = MAX_SIDE_PX) -> list[Image.Image]:
    """RGB frames: each snapshot, then the final map; canvases share the extent and scale
    (the final grid's resolution, shrunk by an integer factor so the longer side <= ``max_side_px``)."""
    states = [(s.grid, s.trajectory) for s in snapshots] + [(final_grid, final_trajectory)]
    res = final_grid.resolution_m
    left = min(g.origin_x_m for g, _ in states)
    bottom = min(g.origin_y_m for g, _ in states)
    right = max(g.origin_x_m + g.shape[1] * g.resolution_m for g, _ in states)
    top = max(g.origin_y_m + g.shape[0] * g.resolution_m for g, _ in states)
    width, height = max(1, round((right - left) / res)), max(1, round((top - bottom) / res))
    shrink = max(1, math.ceil(max(width, height) / max_side_px))
    frames = []
    for grid, trajectory in states:
        canvas = Image.new("RGB", (width, height), (UNKNOWN_GRAY,) * 3)
        image = occupancy_image(grid).convert("RGB")
        if grid.resolution_m != res:
            scale = grid.resolution_m / res
            image = image.resize((max(1, round(image.width * scale)), max(1, round(image.height * scale))),
                                 Image.Resampling.NEAREST)
        top_of_grid = grid.origin_y_m + grid.shape[0] * grid.resolution_m
        canvas.paste(image, (round((grid.origin_x_m - left) / res), round((top - top_of_grid) / res)))
        if len(trajectory) > 1:
            points = [((x - left) / res, (top - y) / res) for x, y in trajectory.poses[:, :2]]
            ImageDraw.Draw(canvas).line(points, fill=TRAJECTORY_RGB, width=max(1, shrink))
        if shrink > 1:
            canvas = canvas.reduce(shrink)
        frames.append(canvas)
    return frames


def write_animation_gif(snapshots: list[MapSnapshot], final_grid: OccupancyGrid, final_trajectory: Trajectory,
                        path: str | Path, max_side_px: int = MAX_SIDE_PX) -> Path:
    """Write the looping GIF (len(snapshots) + 1 frames; Pillow merges identical consecutive frames)."""
    frames = animation_frames(snapshots, final_grid, final_trajectory, max_side_px)
    durations = [FRAME_DURATION_MS] * (len(frames) - 1) + [LAST_FRAME_DURATION_MS]
    with atomic_path(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=durations, loop=0)
    return Path(path)
