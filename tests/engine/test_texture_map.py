"""Texture accumulation on the grid's geometry, pose interpolation, the Kinect model and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.config import TextureConfig
from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import DriveLog, MotionModelKind, RgbdStream, VehicleModel
from slam_engine.model.poses import to_matrix_4x4
from slam_engine.model.result import OccupancyGrid, Trajectory
from slam_engine.texture import TextureAccumulator, build_texture_map
from slam_engine.texture.calibration import thor_kinect_calibration
from slam_engine.texture.projection import estimate_ground_z, interpolate_poses, transform_points
from slam_engine.texture.rgbd import kinect_depth_m, kinect_rgb_pixel, rgbd_frame_points


def grid_4x3() -> OccupancyGrid:
    """4 columns x 3 rows of 0.5 m cells, lower-left corner at (-1, 2)."""
    return OccupancyGrid(np.zeros((3, 4)), 0.5, -1.0, 2.0)


def test_mean_mode_averages_every_observation_in_the_right_cell():
    acc = TextureAccumulator(grid_4x3(), channels=3, mode="mean")
    acc.add(np.array([-0.9, -0.6]), np.array([2.1, 2.4]), np.array([[100, 0, 0], [200, 0, 0]]))  # cell (0, 0)
    acc.add(np.array([-0.75]), np.array([2.25]), np.array([[0, 90, 0]]))  # cell (0, 0) again
    acc.add(np.array([0.9]), np.array([3.4]), np.array([[1, 2, 3]]))  # cell (ix 3, iy 2)
    texture = acc.texture_map()
    np.testing.assert_array_equal(texture.colors[0, 0], [100, 30, 0])
    np.testing.assert_array_equal(texture.colors[2, 3], [1, 2, 3])
    assert texture.counts[0, 0] == 3 and texture.counts[2, 3] == 1 and texture.counts.sum() == 4
    assert (texture.resolution_m, texture.origin_x_m, texture.origin_y_m) == (0.5, -1.0, 2.0)
    assert texture.colors.shape == (3, 4, 3) and texture.counts.shape == (3, 4)


def test_latest_mode_keeps_the_latest_frame_and_outside_points_are_dropped():
    acc = TextureAccumulator(grid_4x3(), channels=3, mode="latest")
    acc.add(np.array([0.1, 0.2]), np.array([2.6, 2.6]), np.array([[10, 10, 10], [30, 30, 30]]))
    acc.add(np.array([0.3, 5.0, -1.01]), np.array([2.7, 2.7, 2.7]), np.array([[90, 80, 70]] * 3))
    texture = acc.texture_map()
    np.testing.assert_array_equal(texture.colors[1, 2], [90, 80, 70])
    assert texture.counts[1, 2] == 3
    assert acc.points_outside == 2 and acc.points_added == 3


def test_gray_accumulator_gives_a_2d_texture_and_converts_colour():
    acc = TextureAccumulator(grid_4x3(), channels=1)
    acc.add(np.array([0.1]), np.array([2.1]), np.array([50]))
    acc.add(np.array([0.1]), np.array([2.1]), np.array([[255, 0, 0]]))  # luma 76.2
    texture = acc.texture_map()
    assert texture.colors.shape == (3, 4)
    assert texture.colors[0, 2] == 63  # mean of 50 and 76.2


def test_accumulator_matches_a_per_point_reference_over_many_frames():
    """Cells and running means equal a plain per-point reference (np.add.at), frame by frame."""
    rng = np.random.default_rng(7)
    grid = OccupancyGrid(np.zeros((40, 60)), 0.05, -1.0, -1.0)
    acc = TextureAccumulator(grid, channels=3, mode="mean")
    sums, counts = np.zeros((40 * 60, 3)), np.zeros(40 * 60)
    for _ in range(5):
        x, y = rng.uniform(-1.2, 2.2, 3000), rng.uniform(-1.2, 1.2, 3000)  # some points off the grid
        colors = rng.integers(0, 256, (3000, 3))
        acc.add(x, y, colors)
        ix, iy = np.floor((x + 1.0) / 0.05).astype(int), np.floor((y + 1.0) / 0.05).astype(int)
        inside = (ix >= 0) & (ix < 60) & (iy >= 0) & (iy < 40)
        np.add.at(sums, iy[inside] * 60 + ix[inside], colors[inside])
        np.add.at(counts, iy[inside] * 60 + ix[inside], 1)
    texture = acc.texture_map()
    np.testing.assert_array_equal(texture.counts.ravel(), counts)
    seen = counts > 0
    reference = np.clip(np.rint(sums[seen] / counts[seen, None]), 0, 255)
    assert np.abs(texture.colors.reshape(-1, 3)[seen] - reference).max() <= 1  # running mean in float32
    assert (texture.colors.reshape(-1, 3)[~seen] == 0).all()


def test_ground_height_does_not_depend_on_the_ransac_seed():
    """Open3D's threaded RANSAC gives a slightly different plane per seed (and per run); the refit to
    its inliers gives one height."""
    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(3, 10, 20_000), rng.uniform(-4, 4, 20_000), rng.normal(-0.02, 0.01, 20_000)]
    clutter = np.c_[rng.uniform(3, 10, 5_000), rng.uniform(-4, 4, 5_000), rng.uniform(0.0, 2.0, 5_000)]
    heights = {estimate_ground_z(np.r_[ground, clutter], seed=seed) for seed in range(6)}
    assert len(heights) == 1  # without the refit: 6 heights up to 4e-5 m apart
    assert heights.pop() == pytest.approx(-0.02, abs=0.001)


def test_interpolated_poses_wrap_the_heading():
    trajectory = Trajectory(np.array([0.0, 1.0, 2.0]), np.array([[0, 0, 3.0], [1, 0, -3.0], [2, 2, -2.9]]))
    poses, valid = interpolate_poses(trajectory, np.array([0.5, 1.5, 2.05, 3.0]), max_gap_s=0.1)
    assert poses[0, 0] == pytest.approx(0.5)
    # Halfway from +3.0 to -3.0 rad through pi, not through 0.
    assert np.cos(poses[0, 2]) == pytest.approx(np.cos(np.pi), abs=1e-3)
    np.testing.assert_allclose(poses[1, :2], [1.5, 1.0])
    np.testing.assert_array_equal(valid, [True, True, True, False])


def test_open3d_transform_matches_the_matrix():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    T = to_matrix_4x4(np.array([1.0, -2.0, 0.7])) @ thor_kinect_calibration().T_vehicle_from_camera
    np.testing.assert_allclose(transform_points(points, T), points @ T[:3, :3].T + T[:3, 3], atol=1e-12)


def test_kinect_model_numbers():
    # dd = -0.00304 * 600 + 3.31 = 1.486 -> depth 1.03 / 1.486 = 0.6931 m; 0 and 2047 are no reading.
    depth = kinect_depth_m(np.array([600, 1000, 0, 2047]))
    assert depth[0] == pytest.approx(1.03 / 1.486)
    assert depth[1] == pytest.approx(1.03 / 0.27)
    assert np.isnan(depth[2:]).all()
    rgb_u, rgb_v = kinect_rgb_pixel(np.array([100.0]), np.array([200.0]), np.array([1.486]))
    assert rgb_u[0] == pytest.approx((526.37 * 100 - 4.5 * 1750.46 * 1.486 + 19276.0) / 585.051)
    assert rgb_v[0] == pytest.approx((526.37 * 200 + 16662.0) / 585.051)


def test_rgbd_points_sit_where_the_depth_says():
    calibration = thor_kinect_calibration()
    disparity = np.full((480, 640), 2047, dtype=np.uint16)
    disparity[242:245, 314:318] = 800  # depth 1.03 / (3.31 - 2.432) = 1.1731 m
    rgb = np.zeros((480, 640, 3), dtype=np.uint8)
    rgb[...] = (10, 20, 30)
    frame = rgbd_frame_points(disparity, rgb, calibration, TextureConfig())
    assert len(frame.points_camera) == 12
    np.testing.assert_allclose(frame.points_camera[:, 2], 1.03 / (3.31 - 0.00304 * 800))
    assert np.abs(frame.points_camera[:, :2]).max() < 0.01  # near the principal point
    np.testing.assert_array_equal(frame.colors, [[10, 20, 30]] * 12)


def test_unreadable_image_is_a_log_format_error(tmp_path):
    missing = tmp_path / "disparity_1.png"
    stream = RgbdStream(depth_t_s=np.array([0.5]), depth_images=[str(missing)], rgb_t_s=np.array([0.5]),
                        rgb_images=[np.zeros((480, 640, 3), np.uint8)], calibration=thor_kinect_calibration())
    log = DriveLog(VehicleModel(kind=MotionModelKind.DIFFERENTIAL), rgbd=stream)
    trajectory = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)))
    with pytest.raises(LogFormatError, match="image file missing") as info:
        build_texture_map(log, trajectory, grid_4x3(), TextureConfig(ground_z_m=0.0))
    assert info.value.location == "rgbd depth frame 0"
    assert info.value.path == str(missing)


def test_unknown_rgbd_model_is_named():
    calibration = thor_kinect_calibration()
    from dataclasses import replace

    with pytest.raises(LogFormatError, match="unknown RGB-D model 'tof'"):
        rgbd_frame_points(np.zeros((4, 4), np.uint16), np.zeros((4, 4, 3), np.uint8), replace(calibration, model="tof"),
                          TextureConfig())
