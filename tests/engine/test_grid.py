"""Tiled copy-on-write particle grids: indexing, growth, sharing between particles."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.grid import TILE, ParticleGrids
from slam_engine.frontend.raycast import insert_scan


def test_world_cell_round_trip_including_negative_coordinates() -> None:
    grids = ParticleGrids(2, 0.05)
    x = np.array([-3.21, -0.01, 0.0, 0.049, 7.5])
    y = np.array([2.0, -0.051, 0.0, -12.3, 0.26])
    gx, gy = grids.world_to_cell(x, y)
    np.testing.assert_array_equal(gx, [-65, -1, 0, 0, 150])
    cx, cy = grids.cell_to_world(gx, gy)
    assert np.all(np.abs(cx - x) <= 0.025 + 1e-12) and np.all(np.abs(cy - y) <= 0.025 + 1e-12)
    gx2, gy2 = grids.world_to_cell(cx, cy)
    np.testing.assert_array_equal(gx2, gx)
    np.testing.assert_array_equal(gy2, gy)


def _one_beam(grids: ParticleGrids, poses: np.ndarray, end_v: tuple[float, float]) -> None:
    insert_scan(grids, poses, np.zeros(2), np.array([end_v]), np.array([True]), 0.9, -0.4, -5.0, 5.0)


def test_grids_grow_with_the_drive_and_keep_what_they_hold() -> None:
    grids = ParticleGrids(1, 0.1)
    _one_beam(grids, np.zeros((1, 3)), (1.0, 0.0))
    before = grids.occupancy_grid(0)
    ix, iy = before.world_to_cell(1.05, 0.05)
    assert before.log_odds[iy, ix] == np.float32(0.9)
    # drive 200 m away in -x and -y: the tables grow, the first wall stays where it was
    _one_beam(grids, np.array([[-200.0, -150.0, 0.0]]), (1.0, 0.0))
    after = grids.occupancy_grid(0)
    assert after.shape[0] * after.resolution_m > 150 and after.shape[1] * after.resolution_m > 200
    ix, iy = after.world_to_cell(1.05, 0.05)
    assert after.log_odds[iy, ix] == np.float32(0.9)
    ix, iy = after.world_to_cell(-198.95, -149.95)
    assert after.log_odds[iy, ix] == np.float32(0.9)


def test_resampled_particles_share_tiles_until_one_writes() -> None:
    grids = ParticleGrids(3, 0.05)
    start = np.tile([0.5, 0.5, 0.0], (3, 1))  # inside the tile [0, 3.2 m)^2, away from its borders
    _one_beam(grids, start, (2.0, 0.0))
    grids.resample(np.array([0, 0, 0]))
    assert grids.tiles_in_use() == 1  # one tile, three readers
    assert np.all(grids.refcount[grids.tables[:, grids.tables[0] >= 0][:, 0]] == 3)
    # particle 0 alone (poses of particles 0..P-1 are given) sees a wall at y = 1 m: it gets a private
    # copy, the others keep reading the shared tile
    insert_scan(grids, start[:1], np.zeros(2), np.array([[0.5, 1.0]]), np.array([True]), 0.9, -0.4, -5, 5)
    assert grids.tiles_in_use() == 2
    g0, g2 = grids.occupancy_grid(0), grids.occupancy_grid(2)
    ix, iy = g0.world_to_cell(1.025, 1.525)
    assert g0.log_odds[iy, ix] == np.float32(0.9) and g2.log_odds[iy, ix] == 0.0
    np.testing.assert_array_equal(grids.occupancy_grid(1).log_odds, g2.log_odds)


def test_resampling_to_fewer_then_more_particles_keeps_their_maps() -> None:
    """An adaptive particle count: resampling may draw fewer particles than the grids hold, then
    more again (up to ``n_particles``); maps stay with their particles, tiles are counted right, and
    the tables grow with the drive at any count."""
    import pytest

    grids = ParticleGrids(4, 0.05)
    start = np.tile([0.5, 0.5, 0.0], (4, 1))
    insert_scan(grids, start, np.zeros(2), np.array([[2.0, 0.0]]), np.array([True]), 0.9, -0.4, -5, 5)
    insert_scan(grids, start[:1], np.zeros(2), np.array([[0.5, 1.0]]), np.array([True]), 0.9, -0.4, -5, 5,
                particles=np.array([3]))  # particle 3 alone sees a second wall
    walled = grids.occupancy_grid(3).log_odds
    grids.resample(np.array([3, 1]))  # two particles: 3's map and 1's
    assert grids.tables.shape[0] == 2 and grids.tiles_in_use() == 2
    np.testing.assert_array_equal(grids.occupancy_grid(0).log_odds, walled)
    # the drive reaches far tiles with two particles, then resamples to four
    insert_scan(grids, np.array([[-50.0, 40.0, 0.0]] * 2), np.zeros(2), np.array([[1.0, 0.0]]), np.array([True]),
                0.9, -0.4, -5, 5)
    grids.resample(np.array([0, 0, 1, 1]))
    assert grids.tables.shape[0] == 4
    far = grids.occupancy_grid(2)
    ix, iy = far.world_to_cell(-48.975, 40.025)
    assert far.log_odds[iy, ix] == np.float32(0.9)
    assert np.all(grids.refcount[grids.refcount > 0] == 2)  # every tile read by the two copies of each map
    with pytest.raises(ValueError, match="at most 4"):
        grids.resample(np.zeros(5, np.int64))


def test_coarse_levels_hold_the_maximum_of_their_cells() -> None:
    grids = ParticleGrids(1, 0.05)
    _one_beam(grids, np.zeros((1, 3)), (1.0, 0.52))
    t = grids.tables[0][grids.tables[0] >= 0][0]
    level0 = grids.levels[0][t]
    for k in range(1, 4):
        f = 1 << k
        expected = level0.reshape(TILE // f, f, TILE // f, f).max(axis=(1, 3))
        np.testing.assert_array_equal(grids.levels[k][t], expected)


def test_stale_tiles_leave_the_particles_maps_but_stay_in_the_preview() -> None:
    grids = ParticleGrids(2, 0.05)
    start = np.tile([0.5, 0.5, 0.0], (2, 1))
    _one_beam(grids, start, (1.0, 0.0))  # a wall at (1.5, 0.5), clock 0 m
    grids.clock_m = 40.0
    far = np.tile([60.5, 0.5, 0.0], (2, 1))
    _one_beam(grids, far, (1.0, 0.0))  # a wall at (61.5, 0.5), clock 40 m
    in_use = grids.tiles_in_use()
    # forget what no scan touched in the last 30 m: the first tile, not the second
    assert grids.forget_stale(grids.clock_m - 30.0, 0, -500, 500) == 1
    assert grids.tiles_in_use() < in_use
    ty = int(np.floor(0.5 / grids.tile_size_m)) - grids.tile_y0
    tx = int(np.floor(1.5 / grids.tile_size_m)) - grids.tile_x0
    assert np.all(grids.tables[:, ty, tx] < 0)  # no particle matches against the old wall any more
    preview = grids.occupancy_grid(0)
    for x in (1.52, 61.52):
        ix, iy = preview.world_to_cell(x, 0.52)
        assert preview.log_odds[iy, ix] == np.float32(0.9)
    # back at the start: the particles' map starts afresh there, the preview adds both passes
    _one_beam(grids, start, (1.0, 0.0))
    live_tile = grids.levels[0][grids.tables[0, ty, tx]]
    gx, gy = grids.world_to_cell(1.52, 0.52)
    assert live_tile[gy % TILE, gx % TILE] == 90  # one hit (0.9 in units of 0.01), not two
    preview = grids.occupancy_grid(0, pool=1)
    ix, iy = preview.world_to_cell(1.52, 0.52)
    assert preview.log_odds[iy, ix] == np.float32(1.8)
    assert grids.occupancy_grid(0, pool=2).shape == preview.pooled(2).shape


def test_pooling_keeps_the_largest_known_value_of_each_block() -> None:
    """A pooled block holds its largest known (non-zero) log-odds, free space below zero included;
    0 only where nothing in the block is known; a partial block at the edge pools what it has."""
    from slam_engine.model.result import OccupancyGrid

    values = np.zeros((5, 5), np.float32)
    values[0, 0], values[1, 1] = -2.0, -0.5  # free only: the less certain free value
    values[0, 2], values[1, 3] = -3.0, 1.5  # a wall beside free space: the wall
    values[4, 4] = -1.0  # the edge's partial block
    pooled = OccupancyGrid(values, 0.05, 1.0, -2.0).pooled(2)
    assert pooled.log_odds.tolist() == [[-0.5, 1.5, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
    assert (pooled.resolution_m, pooled.origin_x_m, pooled.origin_y_m) == (0.1, 1.0, -2.0)


def _scattered_scans(grids: ParticleGrids, rng: np.random.Generator, centre: tuple[float, float], scans: int) -> None:
    """Scans of 60 beams (returns and no-returns) from poses scattered around ``centre`` [m]."""
    angles = np.linspace(-np.pi, np.pi, 60, endpoint=False)
    for _ in range(scans):
        poses = np.column_stack([centre[0] + rng.normal(0, 1.0, grids.n_particles),
                                 centre[1] + rng.normal(0, 1.0, grids.n_particles),
                                 rng.uniform(-np.pi, np.pi, grids.n_particles)])
        ranges = rng.uniform(1.0, 6.0, len(angles))
        ends = np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])
        insert_scan(grids, poses, np.zeros(2), ends, rng.random(len(angles)) < 0.8, 0.9, -0.4, -5.0, 5.0)


def test_pooled_maps_from_tiles_equal_pooling_the_full_map() -> None:
    """A map drawn from the tiles at any pool factor equals the full-resolution map (live tiles plus
    the archive's forgotten ones) pooled afterwards, bit for bit, also where a live and an archived
    value cancel to 0 (unknown)."""
    from slam_engine.model.result import OccupancyGrid

    rng = np.random.default_rng(7)
    grids = ParticleGrids(3, 0.05)
    _scattered_scans(grids, rng, (0.0, 0.0), 6)
    grids.clock_m = 50.0
    _scattered_scans(grids, rng, (40.0, -10.0), 6)
    assert grids.forget_stale(grids.clock_m - 30.0, 1, -500, 500) > 0  # the first place is archived
    archived = len(grids.archive)
    grids.clock_m = 60.0
    _scattered_scans(grids, rng, (0.0, 0.0), 3)  # back there: live tiles over the archived ones
    assert len(grids.archive) == archived and archived > 0
    # a live value that cancels its archived one: the sum 0 is unknown, as in the full map
    cancelled = 0
    for (ty, tx), kept in grids.archive.items():
        live = grids.tables[1, ty - grids.tile_y0, tx - grids.tile_x0]
        if live >= 0 and grids.refcount[live] == 1 and np.any(kept != 0):
            iy, ix = np.argwhere(kept != 0)[0]
            grids.levels[0][live, iy, ix] = -kept[iy, ix]
            cancelled += 1
    assert cancelled > 0
    full = grids.occupancy_grid(1)
    # the full map assembled here tile by tile: live plus archived stored values, / 100 as float32
    r0 = int(np.floor(full.origin_y_m / grids.tile_size_m + 0.5)) - grids.tile_y0
    c0 = int(np.floor(full.origin_x_m / grids.tile_size_m + 0.5)) - grids.tile_x0
    stored = np.zeros(full.shape, np.int32)
    for (r, c), t in np.ndenumerate(grids.tables[1]):
        if t >= 0:
            stored[(r - r0) * TILE:(r - r0 + 1) * TILE, (c - c0) * TILE:(c - c0 + 1) * TILE] += grids.levels[0][t]
    for (ty, tx), kept in grids.archive.items():
        r, c = ty - grids.tile_y0 - r0, tx - grids.tile_x0 - c0
        stored[r * TILE:(r + 1) * TILE, c * TILE:(c + 1) * TILE] += kept
    np.testing.assert_array_equal(full.log_odds, stored.astype(np.float32) / np.float32(100.0))
    assert np.any(full.log_odds > 0) and np.any(full.log_odds < 0)
    for pool in range(1, 8):
        pooled = grids.occupancy_grid(1, pool=pool)
        expected = OccupancyGrid(full.log_odds, full.resolution_m, full.origin_x_m, full.origin_y_m).pooled(pool)
        assert pooled.log_odds.shape == expected.log_odds.shape
        np.testing.assert_array_equal(pooled.log_odds.view(np.uint32), expected.log_odds.view(np.uint32))
        assert (pooled.resolution_m, pooled.origin_x_m, pooled.origin_y_m) == (
            expected.resolution_m, expected.origin_x_m, expected.origin_y_m)


def test_archive_grows_without_moving_the_tiles_it_holds() -> None:
    grids = ParticleGrids(1, 0.05)
    rng = np.random.default_rng(1)
    views = []
    for k in range(6):  # each place is forgotten once the drive is 30 m further on
        grids.clock_m = 40.0 * k
        _scattered_scans(grids, rng, (40.0 * k, 0.0), 2)
        grids.forget_stale(grids.clock_m - 30.0, 0, -500, 500)
        views.append({key: tile.copy() for key, tile in grids.archive.items()})
    assert len(grids.archive) > 16  # the stack grew at least once
    for key, tile in views[1].items():  # tiles archived early still hold their values
        np.testing.assert_array_equal(grids.archive[key], tile)
    grids.keep_only(None)
    assert grids.archive == {} and grids.memory_bytes() < 10**6


def test_render_frames_pooled_from_tiles_equal_the_full_frames_reduced() -> None:
    """The animation's frames drawn at the final poses come pooled from the tiles (at most
    ``frame_max_side_cells`` a side): bit for bit what reducing each full-resolution frame gives."""
    from slam_engine.backend.map_builder import render_occupancy
    from slam_engine.config import GridConfig
    from slam_engine.frontend.lidar_points import ProjectedScan
    from slam_engine.model.result import MapSnapshot, OccupancyGrid, Trajectory

    rng = np.random.default_rng(3)
    angles = np.linspace(-np.pi, np.pi, 180, endpoint=False)
    scans, poses = [], []
    for k in range(12):  # a drive along x: the map, and so the frames' pool factor, grows
        ranges = rng.uniform(2.0, 8.0, len(angles))
        ends = np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], axis=1)
        scans.append(ProjectedScan(ends, rng.random(len(angles)) < 0.8, np.zeros(len(angles))))
        poses.append([1.5 * k, 0.2 * k, 0.1 * k])
    frames_after = {1, 4, 8, 12}
    full: dict[int, OccupancyGrid] = {}
    pooled: dict[int, OccupancyGrid] = {}
    config = GridConfig(resolution_m=0.05)
    render_occupancy(scans, np.array(poses), np.zeros(2), config, frames_after, lambda n, g: full.__setitem__(n, g))
    render_occupancy(scans, np.array(poses), np.zeros(2), config, frames_after,
                     lambda n, g: pooled.__setitem__(n, g), frame_max_side_cells=100)
    trajectory = Trajectory(np.zeros(1), np.zeros((1, 3)))
    factors = set()
    for n in sorted(frames_after):
        expected = MapSnapshot(-1, 0.0, full[n], trajectory).reduced(100).grid
        got = pooled[n]
        factors.add(round(got.resolution_m / 0.05))
        assert got.log_odds.shape == expected.log_odds.shape
        np.testing.assert_array_equal(got.log_odds.view(np.uint32), expected.log_odds.view(np.uint32))
        assert (got.resolution_m, got.origin_x_m, got.origin_y_m) == (
            expected.resolution_m, expected.origin_x_m, expected.origin_y_m)
    assert len(factors) > 1  # frames pooled by more than one factor as the map grew
