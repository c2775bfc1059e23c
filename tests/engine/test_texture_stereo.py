"""Stereo depth on the ECE276A car's real stereo pair (raw Bayer frames, 1280x560)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from slam_engine.config import TextureConfig
from slam_engine.texture.calibration import load_ece276a_stereo_calibration
from slam_engine.texture.images import demosaic, read_frame
from slam_engine.texture.projection import estimate_ground_z, transform_points
from slam_engine.texture.stereo import (
    StereoRectifier,
    back_project,
    compute_disparity,
    depth_from_disparity,
    stereo_frame_points,
)


@pytest.fixture
def car_pair(dataset):
    return _car_pair(str(dataset("ece276a-car")))


@functools.cache
def _car_pair(root_dir: str):
    """Calibration, rectifier, raw frames, disparity and depth of the sample pair (computed once)."""
    root = Path(root_dir)
    cal = load_ece276a_stereo_calibration(root / "param")
    left = read_frame(root / "stereo_sample" / "image_left.png", "left")
    right = read_frame(root / "stereo_sample" / "image_right.png", "right")
    rectifier = StereoRectifier(cal)
    left_rect, right_rect = rectifier.rectify(left, right)
    disparity = compute_disparity(left_rect, right_rect, TextureConfig())
    depth = depth_from_disparity(disparity, rectifier.fx_px, cal.baseline_m)
    return cal, rectifier, left, right, disparity, depth


def test_rectified_disparity_covers_the_road(car_pair):
    cal, _, left, right, disparity, _ = car_pair
    lower = disparity[disparity.shape[0] // 2:]
    valid_rectified = np.isfinite(lower).mean()
    assert valid_rectified > 0.5  # measured 0.56
    # Matching the raw (unrectified) frames finds about half as many: rectification matters.
    raw = compute_disparity(demosaic(left, "BG"), demosaic(right, "BG"), TextureConfig())
    assert valid_rectified > 1.5 * np.isfinite(raw[raw.shape[0] // 2:]).mean()  # measured 0.28


def test_road_depths_between_2_and_40_m_growing_towards_the_horizon(car_pair):
    _, rectifier, _, _, _, depth = car_pair
    lower = depth[depth.shape[0] // 2:]
    valid = lower[np.isfinite(lower)]
    assert ((valid > 2.0) & (valid < 40.0)).mean() > 0.95  # measured 0.984
    band_medians = [np.nanmedian(depth[rows]) for rows in (slice(500, 540), slice(440, 480),
                                                           slice(360, 400), slice(300, 330))]
    assert np.all(np.diff(band_medians) > 0), band_medians  # measured 4.6, 5.8, 9.0, 16.1 m
    # Low rows see the road where a flat road 1.584 m below the camera puts it (+-5 %). (Rows below
    # ~540 of the rectified image lie outside the raw image: the rectified view is wider.)
    for row in (470, 500, 530):
        ray = np.linalg.inv(rectifier.T_vehicle_from_rectified[:3, :3]).T @ [
            (640 - rectifier.cx_px) / rectifier.fx_px, (row - rectifier.cy_px) / rectifier.fy_px, 1.0]
        expected_depth = rectifier.T_vehicle_from_rectified[2, 3] / -ray[2]  # optical z at which z_vehicle = 0
        assert np.nanmedian(depth[row - 2:row + 3]) == pytest.approx(expected_depth, rel=0.05)  # measured within 2 %


def test_road_plane_is_at_the_vehicle_origin_height(car_pair):
    cal, rectifier, _, _, _, depth = car_pair
    points = back_project(depth, rectifier.fx_px, rectifier.fy_px, rectifier.cx_px, rectifier.cy_px)
    points = points[depth.shape[0] // 2:].reshape(-1, 3)
    points = points[np.isfinite(points[:, 2]) & (points[:, 2] < 25.0)]
    ground_z = estimate_ground_z(transform_points(points, rectifier.T_vehicle_from_rectified))
    assert ground_z is not None and abs(ground_z) < 0.1  # measured 0.014 m


def test_frame_points_are_coloured_and_within_the_depth_range(car_pair):
    cal, rectifier, left, right, _, _ = car_pair
    config = TextureConfig(max_depth_m=12.0)
    frame = stereo_frame_points(left, right, rectifier, config)
    assert frame.colors.shape == (len(frame.points_camera), 3)  # Bayer frames give colour
    assert frame.points_camera[:, 2].min() >= config.min_depth_m
    assert frame.points_camera[:, 2].max() <= 12.0
    assert len(frame.points_camera) > 80_000  # measured 107 259 (144 291 matching the full width)


def test_ground_window_matches_only_the_rows_that_see_the_ground(car_pair):
    """The rows whose rays meet the ground band within 0.3-10 m: below the horizon (row ~257) only;
    matched alone, they give the ground points that matching the whole image gives."""
    cal, rectifier, left, right, _, _ = car_pair
    config = TextureConfig()
    window = rectifier.ground_window(0.0, config)
    assert window is not None
    height = int(cal.image_size_wh[1])
    # 10 m ahead, 1.58 m down: row cy + f h / z ~ 380; the window starts a margin above that
    assert 320 < window.row_start < 370 and window.row_stop == height  # measured 341:560
    # ground 1.58 m below the cameras is never within 1 m of them: nothing to match
    assert rectifier.ground_window(0.0, TextureConfig(max_depth_m=1.0)) is None

    def ground_points(frame):
        world = transform_points(frame.points_camera, frame.T_vehicle_from_camera)
        return world[np.abs(world[:, 2]) <= config.ground_band_m]

    whole = ground_points(stereo_frame_points(left, right, rectifier, config))
    windowed = ground_points(stereo_frame_points(left, right, rectifier, config, window=window))
    assert len(windowed) == pytest.approx(len(whole), rel=0.03)  # measured 80 745 and 81 383
    # the same ground: per 0.5 m ground square, about the same points (a point that moved counts twice)
    bins = (np.arange(0, 12.5, 0.5), np.arange(-10, 10.5, 0.5))
    h_whole = np.histogram2d(whole[:, 0], whole[:, 1], bins)[0]
    h_windowed = np.histogram2d(windowed[:, 0], windowed[:, 1], bins)[0]
    assert np.abs(h_whole - h_windowed).sum() < 0.06 * len(whole)  # measured 0.030


def test_narrowed_matching_sees_the_road_the_full_width_sees(car_pair):
    """Matching the pair at half its width (the default) puts the road at the same height and range
    and covers at least as many 5 cm ground cells as matching it whole."""
    cal, rectifier, left, right, _, _ = car_pair

    def ground(scale):
        config = TextureConfig(stereo_width_scale=scale)
        frame = stereo_frame_points(left, right, rectifier, config)
        world = transform_points(frame.points_camera, frame.T_vehicle_from_camera)
        return world[np.abs(world[:, 2]) <= config.ground_band_m]

    full, narrowed = ground(1.0), ground(0.5)
    assert np.median(narrowed[:, 2]) == pytest.approx(np.median(full[:, 2]), abs=0.005)  # measured -0.029, -0.029 m
    ahead = np.arange(5.0, 13.0, 1.0)
    share_full = np.histogram(full[:, 0], ahead)[0] / len(full)
    share_narrowed = np.histogram(narrowed[:, 0], ahead)[0] / len(narrowed)
    assert np.abs(share_full - share_narrowed).max() < 0.05  # measured 0.032
    cells = [len(np.unique(np.floor(points[:, :2] / 0.05), axis=0)) for points in (full, narrowed)]
    assert cells[1] > cells[0]  # measured 12 752 against 9 262: fewer pixels, more of them matched
