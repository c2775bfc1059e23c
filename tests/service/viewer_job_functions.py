"""A job function for the viewer tests: a known room mapped step by step, no SLAM involved.

The room's walls are at x = 0 and x = ROOM_X_M, y = 0 and y = ROOM_Y_M (map frame, metres); a pillar
(one PILLAR_SIZE_M square) has its lower-left corner at PILLAR_XY_M, so a test can tell whether the viewer
places the map the right way round. The robot drives around the room; after step ``i`` of
``config.particles`` the live grid holds the cells seen so far (the walls appear in order), and each step
takes ``config.seed`` milliseconds. The job ends by writing every product as the mapping job does,
with a ground texture: the floor as a 1 m green/yellow checkerboard.
"""

from __future__ import annotations

import time

import numpy as np

from service.jobs.products import GRID_FILE, TEXTURE_FILE, save_grid, save_texture
from service.jobs.settings import engine_config
from slam_engine.config import SlamConfig
from slam_engine.model.result import OccupancyGrid, ScanStats, SlamResult, TextureMap, Trajectory
from slam_engine.products import write_products
from slam_engine.progress import MAPPING_SCANS, WRITING_PRODUCTS, run_fraction

ROOM_X_M, ROOM_Y_M = 12.0, 8.0
PILLAR_XY_M, PILLAR_SIZE_M = (8.0, 5.0), 1.0
MARGIN_M = 1.0
OCCUPIED_LOG_ODDS, FREE_LOG_ODDS = 4.0, -2.0
FLOOR_COLORS = np.array([[40, 160, 60], [230, 200, 40]], dtype=np.uint8)  # green / yellow 1 m checkerboard


def room_trajectory(steps: int) -> Trajectory:
    """A loop 1.5 m inside the walls, counter-clockwise from (1.5, 1.5), ``steps`` poses."""
    corners = np.array([[1.5, 1.5], [ROOM_X_M - 1.5, 1.5], [ROOM_X_M - 1.5, ROOM_Y_M - 1.5],
                        [1.5, ROOM_Y_M - 1.5], [1.5, 1.5]])
    lengths = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    s = np.linspace(0.0, lengths.sum(), steps)
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    xy = np.column_stack([np.interp(s, cumulative, corners[:, 0]), np.interp(s, cumulative, corners[:, 1])])
    heading = np.unwrap(np.arctan2(*np.gradient(xy, axis=0).T[::-1]))
    return Trajectory(t_s=np.arange(steps) * 0.1, poses=np.column_stack([xy, heading]))


def room_grid(resolution_m: float, seen_fraction: float) -> OccupancyGrid:
    """The room's grid with cells within reach of the first ``seen_fraction`` of the loop known."""
    origin = -MARGIN_M
    width = int(round((ROOM_X_M + 2 * MARGIN_M) / resolution_m))
    height = int(round((ROOM_Y_M + 2 * MARGIN_M) / resolution_m))
    x = origin + (np.arange(width) + 0.5) * resolution_m
    y = origin + (np.arange(height) + 0.5) * resolution_m
    cx, cy = np.meshgrid(x, y)
    wall = (np.abs(cx) < 0.1) | (np.abs(cx - ROOM_X_M) < 0.1) | (np.abs(cy) < 0.1) | (np.abs(cy - ROOM_Y_M) < 0.1)
    wall &= (cx > -0.1) & (cx < ROOM_X_M + 0.1) & (cy > -0.1) & (cy < ROOM_Y_M + 0.1)
    px, py = PILLAR_XY_M
    pillar = (cx >= px) & (cx < px + PILLAR_SIZE_M) & (cy >= py) & (cy < py + PILLAR_SIZE_M)
    inside = (cx > 0.1) & (cx < ROOM_X_M - 0.1) & (cy > 0.1) & (cy < ROOM_Y_M - 0.1)
    log_odds = np.zeros((height, width), dtype=np.float32)
    log_odds[inside] = FREE_LOG_ODDS
    log_odds[wall | pillar] = OCCUPIED_LOG_ODDS
    # Cells are revealed by angle around the room's centre, as the robot goes round.
    angle = np.mod(np.arctan2(cy - ROOM_Y_M / 2, cx - ROOM_X_M / 2) + np.pi * 0.75, 2 * np.pi) / (2 * np.pi)
    log_odds[angle > seen_fraction] = 0.0
    return OccupancyGrid(log_odds=log_odds, resolution_m=resolution_m, origin_x_m=origin, origin_y_m=origin)


def room_texture(grid: OccupancyGrid) -> TextureMap:
    """The floor (free cells) as a 1 m green/yellow checkerboard; walls and the pillar never seen."""
    h, w = grid.log_odds.shape
    ix, iy = np.meshgrid(np.arange(w), np.arange(h))
    x_m = grid.origin_x_m + (ix + 0.5) * grid.resolution_m
    y_m = grid.origin_y_m + (iy + 0.5) * grid.resolution_m
    colors = FLOOR_COLORS[(np.floor(x_m) + np.floor(y_m)).astype(int) % 2]
    counts = np.where(grid.log_odds < 0, 3, 0).astype(np.int32)
    return TextureMap(colors=colors, counts=counts, resolution_m=grid.resolution_m, origin_x_m=grid.origin_x_m,
                      origin_y_m=grid.origin_y_m)


def room_result(resolution_m: float, steps: int) -> SlamResult:
    trajectory = room_trajectory(steps)
    drift = np.column_stack([np.linspace(0, 0.8, steps), np.linspace(0, -0.5, steps), np.zeros(steps)])
    dead_reckoning = Trajectory(t_s=trajectory.t_s, poses=trajectory.poses + drift)
    stats = ScanStats(t_s=trajectory.t_s, n_eff=np.full(steps, 10.0), resampled=np.zeros(steps, bool),
                      match_score=np.ones(steps), matched=np.ones(steps, bool), step_time_s=np.full(steps, 1e-3))
    grid = room_grid(resolution_m, 1.0)
    return SlamResult(trajectory=trajectory, dead_reckoning=dead_reckoning, grid=grid, scan_stats=stats,
                      config=SlamConfig(), texture=room_texture(grid))


def synthetic_room(ctx) -> None:
    """``particles`` steps of ``seed`` ms each, a growing live grid (unless ``snapshot_every_scans`` is 0),
    then every product."""
    config = engine_config(ctx.job.config)
    steps = max(2, config.particles)
    step_s = config.seed / 1000.0
    resolution_m = config.grid.resolution_m
    live = ctx.data.live_dir(ctx.job_id)
    live.mkdir(parents=True, exist_ok=True)
    live_map = config.snapshot_every_scans > 0
    for i in range(1, steps + 1):
        if live_map:
            save_grid(room_grid(resolution_m, i / steps), live / GRID_FILE)
        ctx.progress(i, steps, force=True, stage=MAPPING_SCANS, fraction=run_fraction(MAPPING_SCANS, i / steps))
        time.sleep(step_s)
    ctx.stage(WRITING_PRODUCTS)
    result = room_result(resolution_m, steps)
    written = write_products(result, ctx.out_dir)
    save_grid(result.grid, ctx.out_dir / GRID_FILE)
    save_texture(result.texture, ctx.out_dir / TEXTURE_FILE)
    ctx.store.set_products(ctx.job_id, {path.name: path.name for path in written.values()})
