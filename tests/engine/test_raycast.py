"""Ray casting marks exactly the expected cells."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.grid import ParticleGrids
from slam_engine.frontend.lidar_points import ScanProjector, bracketed_no_return_m, free_space_start_m
from slam_engine.frontend.raycast import insert_scan
from slam_engine.model.drive_log import LidarModel


def _cells(grid) -> dict[tuple[int, int], float]:
    """{(ix, iy) in global cells: log-odds} of the non-zero cells."""
    iy, ix = np.nonzero(grid.log_odds)
    gx = ix + int(round(grid.origin_x_m / grid.resolution_m))
    gy = iy + int(round(grid.origin_y_m / grid.resolution_m))
    return {(int(a), int(b)): round(float(grid.log_odds[i, j]), 6) for a, b, i, j in zip(gx, gy, iy, ix, strict=True)}


def test_beam_along_x_misses_then_hits() -> None:
    grids = ParticleGrids(1, 0.1)
    insert_scan(grids, np.zeros((1, 3)), np.array([0.05, 0.05]), np.array([[0.55, 0.05]]), np.array([True]),
                0.9, -0.4, -5.0, 5.0)
    assert _cells(grids.occupancy_grid(0)) == {(0, 0): -0.4, (1, 0): -0.4, (2, 0): -0.4, (3, 0): -0.4,
                                              (4, 0): -0.4, (5, 0): 0.9}


def test_no_return_beam_clears_its_whole_length_and_adds_no_hit() -> None:
    grids = ParticleGrids(1, 0.1)
    ends = np.array([[0.55, 0.05], [0.05, 0.35]])
    insert_scan(grids, np.zeros((1, 3)), np.array([0.05, 0.05]), ends, np.array([True, False]), 0.9, -0.4, -5, 5)
    cells = _cells(grids.occupancy_grid(0))
    assert cells[(0, 0)] == -0.8  # crossed by both beams
    assert [cells[(0, k)] for k in (1, 2, 3)] == [-0.4, -0.4, -0.4]
    assert cells[(5, 0)] == 0.9 and len(cells) == 9


def test_diagonal_beam_from_a_rotated_pose() -> None:
    grids = ParticleGrids(1, 0.1)
    # vehicle at (0.05, 0.05) facing 45 deg, beam 0.4 * sqrt(2) m straight ahead: cells (k, k)
    d = 0.4 * np.sqrt(2)
    insert_scan(grids, np.array([[0.05, 0.05, np.pi / 4]]), np.zeros(2), np.array([[d, 0.0]]), np.array([True]),
                0.9, -0.4, -5.0, 5.0)
    assert _cells(grids.occupancy_grid(0)) == {(0, 0): -0.4, (1, 1): -0.4, (2, 2): -0.4, (3, 3): -0.4,
                                              (4, 4): 0.9}


def test_clamping_and_hits_win_over_same_scan_misses() -> None:
    grids = ParticleGrids(1, 0.1)
    # beam 1 ends at (3, 0); beam 2 runs through that cell to (6, 0): the cell keeps its hit
    ends = np.array([[0.35, 0.05], [0.65, 0.05]])
    for _ in range(20):
        insert_scan(grids, np.zeros((1, 3)), np.array([0.05, 0.05]), ends, np.array([True, True]), 0.9, -0.4,
                    -2.0, 3.0)
    cells = _cells(grids.occupancy_grid(0))
    assert cells[(0, 0)] == -2.0 and cells[(6, 0)] == 3.0
    assert cells[(3, 0)] == 3.0  # +0.9 - 0.4 per scan, clamped at 3.0


def test_projector_keeps_no_return_beams_as_free_rays() -> None:
    lidar = LidarModel(num_beams=3, angle_min_rad=-np.pi / 2, angle_increment_rad=np.pi / 2, range_min_m=0.1,
                       range_max_m=20.0)
    projector = ScanProjector(lidar, max_range_m=10.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05)
    scan = projector.project(np.array([2.0, np.inf, 15.0]))
    np.testing.assert_allclose(scan.ends_v, [[0.0, -2.0], [10.0, 0.0], [0.0, 10.0]], atol=1e-12)
    np.testing.assert_array_equal(scan.is_hit, [True, False, False])
    np.testing.assert_allclose(scan.hits_v, [[0.0, -2.0]], atol=1e-12)


def test_projector_turns_each_scan_by_its_own_angle_offset() -> None:
    # a LiDAR mounted 0.5 m ahead, turned 90 deg left; a scan whose beams start 0.25 deg further left
    mount = np.eye(4)
    mount[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    mount[0, 3] = 0.5
    lidar = LidarModel(num_beams=3, angle_min_rad=-np.pi / 2, angle_increment_rad=np.pi / 2, range_min_m=0.1,
                       range_max_m=20.0, T_vehicle_from_lidar=mount)
    projector = ScanProjector(lidar, max_range_m=10.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05)
    ranges = np.array([2.0, 3.0, 4.0])
    plain = projector.project(ranges)
    np.testing.assert_allclose(plain.ends_v, [[2.5, 0.0], [0.5, 3.0], [-3.5, 0.0]], atol=1e-12)
    offset = np.radians(0.25)
    turned = projector.project(ranges, angle_offset_rad=offset)
    angles = np.array([-np.pi / 2, 0.0, np.pi / 2]) + offset + np.pi / 2  # in the vehicle frame
    expected = np.array([0.5, 0.0]) + ranges[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    np.testing.assert_allclose(turned.ends_v, expected, atol=1e-12)
    assert not np.allclose(turned.ends_v, plain.ends_v, atol=1e-3)
    # an offset of zero is the model's geometry exactly
    np.testing.assert_array_equal(projector.project(ranges, angle_offset_rad=0.0).ends_v, plain.ends_v)


def test_projector_drops_ground_hits_of_a_tilted_lidar() -> None:
    # LiDAR 1 m up, pitched down 10 deg: a return at 3 m lands at z = 1 - 3 sin(10 deg) = 0.48 m (kept),
    # one at 8 m at z = -0.39 m (ground: dropped)
    pitch = np.radians(10.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]]
    T[2, 3] = 1.0
    lidar = LidarModel(num_beams=2, angle_min_rad=0.0, angle_increment_rad=0.0, range_min_m=0.1, range_max_m=30.0,
                       T_vehicle_from_lidar=T)
    projector = ScanProjector(lidar, max_range_m=30.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05)
    scan = projector.project(np.array([3.0, 8.0]))
    np.testing.assert_allclose(scan.ends_v, [[3.0 * np.cos(pitch), 0.0]], atol=1e-9)
    np.testing.assert_array_equal(scan.is_hit, [True])


def test_free_space_thinning_keeps_beams_half_a_cell_apart() -> None:
    start = free_space_start_m(8, np.radians(1.0), 0.05)
    one = 0.05 / np.radians(1.0)  # 2.86 m: where 1-deg neighbours are a cell apart
    np.testing.assert_allclose(start, [0.0, one, one / 2, one, one / 4, one, one / 2, one])
    # a thinned beam still ends with its hit and clears from its start on
    grids = ParticleGrids(1, 0.1)
    insert_scan(grids, np.zeros((1, 3)), np.array([0.05, 0.05]), np.array([[0.55, 0.05], [0.2, 0.05]]),
                np.array([True, True]), 0.9, -0.4, -5.0, 5.0, free_from_m=np.array([0.3, 0.3]))
    assert _cells(grids.occupancy_grid(0)) == {(3, 0): -0.4, (4, 0): -0.4, (5, 0): 0.9, (2, 0): 0.9}


def test_no_return_beams_can_be_left_out() -> None:
    lidar = LidarModel(num_beams=3, angle_min_rad=-np.pi / 2, angle_increment_rad=np.pi / 2, range_min_m=0.1,
                       range_max_m=20.0)
    projector = ScanProjector(lidar, max_range_m=10.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05,
                              no_return_clear_m=0.0)
    scan = projector.project(np.array([2.0, np.inf, 15.0]))
    # the no-return beam is gone; the over-range return still clears to max_range_m
    np.testing.assert_allclose(scan.ends_v, [[0.0, -2.0], [0.0, 10.0]], atol=1e-12)
    np.testing.assert_array_equal(scan.is_hit, [True, False])
    assert len(scan.free_from_m) == 2


def test_insertion_into_shared_tiles_writes_every_cell_a_private_map_gets() -> None:
    """Writing into tiles shared after resampling copies exactly the tiles the rays reach: no cell update
    is lost at tile borders (Bresenham cells stray from the exact line; beams start part-way)."""
    rng = np.random.default_rng(1)
    angles = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    cover = 20.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # no-return rays: every tile near by
    n = 3000
    theta = rng.uniform(-np.pi, np.pi, n)
    ends = rng.uniform(0.5, 15.0, n)[:, None] * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    is_hit = rng.random(n) < 0.7
    free_from = rng.uniform(0.0, 2.0, n)
    pose = np.array([[0.37, -0.81, 0.3]])
    origin = np.array([0.12, 0.05])

    shared = ParticleGrids(2, 0.05)
    insert_scan(shared, np.repeat(pose, 2, axis=0), origin, cover, np.zeros(len(cover), bool), 0.9, -0.4, -5, 5)
    shared.resample(np.array([0, 0]))
    insert_scan(shared, pose, origin, ends, is_hit, 0.9, -0.4, -5, 5, free_from, particles=np.array([0]))

    private = ParticleGrids(1, 0.05)
    insert_scan(private, pose, origin, cover, np.zeros(len(cover), bool), 0.9, -0.4, -5, 5)
    insert_scan(private, pose, origin, ends, is_hit, 0.9, -0.4, -5, 5, free_from)
    np.testing.assert_array_equal(shared.occupancy_grid(0).log_odds, private.occupancy_grid(0).log_odds)


def test_no_return_beams_of_a_short_range_scanner_clear_nothing() -> None:
    """A URG-04LX (5.6 m) reports no return for dark surfaces within range: those beams clear nothing;
    a long-range scanner's no-return beams clear up to ``no_return_clear_m``."""
    ranges = np.array([2.0, np.inf, np.inf])
    for range_max_m, expected_rays in ((5.6, 1), (30.0, 3)):
        lidar = LidarModel(num_beams=3, angle_min_rad=-0.1, angle_increment_rad=0.1, range_min_m=0.02,
                           range_max_m=range_max_m)
        projector = ScanProjector(lidar, max_range_m=30.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05,
                                  no_return_clear_m=30.0, no_return_min_sensor_range_m=10.0)
        projected = projector.project(ranges)
        assert len(projected.ends_v) == expected_rays and projected.is_hit.sum() == 1


def _fan(n: int = 61, range_max_m: float = 80.0) -> LidarModel:
    """A level LiDAR at the vehicle origin, beams from -30 to +30 deg, 1 deg apart."""
    return LidarModel(num_beams=n, angle_min_rad=np.radians(-30.0), angle_increment_rad=np.radians(1.0),
                      range_min_m=0.1, range_max_m=range_max_m)


def test_no_return_beams_through_a_window_stop_short_of_the_wall() -> None:
    """A wall at x = 5 m with a window between -10 and +10 deg: the window's beams clear up to 0.5 m
    (``no_return_stop_short_m``) before the wall's line, not 30 m beyond it."""
    lidar = _fan()
    angles = lidar.beam_angles_rad
    ranges = 5.0 / np.cos(angles)
    window = np.abs(np.degrees(angles)) < 10.5
    ranges[window] = np.inf
    projector = ScanProjector(lidar, max_range_m=30.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05,
                              no_return_clear_m=30.0, no_return_bounded=True, no_return_stop_short_m=0.5)
    scan = projector.project(ranges)
    free_ends = scan.ends_v[~scan.is_hit]
    assert len(free_ends) == window.sum() == 21
    length = np.hypot(*free_ends.T)
    np.testing.assert_allclose(length, 5.0 / np.cos(angles[window]) - 0.5, atol=1e-9)
    # unbounded (the old behaviour) they run 30 m, through the wall
    unbounded = ScanProjector(lidar, max_range_m=30.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05,
                              no_return_clear_m=30.0).project(ranges)
    np.testing.assert_allclose(np.hypot(*unbounded.ends_v[~unbounded.is_hit].T), 30.0)


def test_bracketed_no_return_bounds_at_edges_and_in_open_space() -> None:
    lidar = _fan(5)
    dirs = np.stack([np.cos(lidar.beam_angles_rad), np.sin(lidar.beam_angles_rad)], axis=1)
    # a run at the scan's edge: the one bracketing return's range; no return at all: no bound
    ranges = np.array([np.inf, np.inf, 4.0, 6.0, np.inf])
    bound = bracketed_no_return_m(ranges, np.isfinite(ranges), dirs)
    assert bound[0] == bound[1] == 4.0 and bound[4] == 6.0
    assert np.isinf(bracketed_no_return_m(np.full(5, np.inf), np.zeros(5, bool), dirs)).all()
    # between returns at 2 m and 8 m the bound is where the beam meets the line joining them
    ranges = np.array([2.0, np.inf, np.inf, np.inf, 8.0])
    bound = bracketed_no_return_m(ranges, np.isfinite(ranges), dirs)
    a, b = dirs[0] * 2.0, dirs[4] * 8.0
    for k in (1, 2, 3):
        point = dirs[k] * bound[k]
        cross = (b - a)[0] * (point - a)[1] - (b - a)[1] * (point - a)[0]
        assert abs(cross) < 1e-9 and 2.0 < bound[k] < 8.0
    projector = ScanProjector(lidar, max_range_m=30.0, ground_z_m=0.2, ceiling_z_m=3.0, resolution_m=0.05,
                              no_return_clear_m=30.0, no_return_bounded=True)
    scan = projector.project(np.full(5, np.inf))  # open field: every beam clears the whole 30 m
    np.testing.assert_allclose(np.hypot(*scan.ends_v.T), 30.0)


def test_tilted_lidars_keep_clearing_their_sky_beams() -> None:
    """The car's LMS511 fans up over the street: its no-return beams stay as long as the height band
    allows, bounded or not (bounding them would drop the street ahead)."""
    pitch = np.radians(30.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(pitch), 0, -np.sin(pitch)], [0, 1, 0], [np.sin(pitch), 0, np.cos(pitch)]]  # looks up
    T[2, 3] = 1.0
    lidar = LidarModel(num_beams=3, angle_min_rad=-0.1, angle_increment_rad=0.1, range_min_m=0.1, range_max_m=80.0,
                       T_vehicle_from_lidar=T)
    ranges = np.array([3.0, np.inf, 3.0])
    ends = [ScanProjector(lidar, 30.0, 0.2, 20.0, 0.05, 30.0, no_return_bounded=bounded).project(ranges).ends_v
            for bounded in (False, True)]
    np.testing.assert_allclose(ends[0], ends[1])
    assert ends[1][1, 0] > 25.0  # leaves the 20 m ceiling about 33 m out
