"""A SLAM run on a log with camera frames returns the ground texture on the map's own cells."""

from __future__ import annotations

import dataclasses

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.model.result import Trajectory
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate
from slam_engine.simulation.camera_render import render_rgbd_stream
from slam_engine.texture.calibration import thor_kinect_calibration


def colour_error(result, drive, shift_m: float = 0.0) -> float:
    """Mean absolute colour difference between the texture and the true floor (shifted by ``shift_m``)
    over observed cells; the map frame starts at the first true pose."""
    iy, ix = np.nonzero(result.texture.counts > 0)
    x_map, y_map = result.grid.cell_to_world(ix, iy)
    x0, y0, theta0 = drive.ground_truth.poses[0]
    c, s = np.cos(theta0), np.sin(theta0)
    x_world = x0 + c * x_map - s * y_map + shift_m
    y_world = y0 + s * x_map + c * y_map + shift_m
    truth = drive.world.floor_rgb(x_world, y_world).astype(np.float64)
    return float(np.abs(result.texture.colors[iy, ix].astype(np.float64) - truth).mean())


def test_run_slam_builds_the_texture_on_the_grid() -> None:
    drive = simulate("office", seed=0, rig="robot", max_duration_s=20)
    frames = np.arange(0, len(drive.ground_truth), 6)
    camera_path = Trajectory(drive.ground_truth.t_s[frames], drive.ground_truth.poses[frames])
    rgbd = render_rgbd_stream(drive.world.floor_rgb, camera_path, thor_kinect_calibration(), supersample=1)
    result = run_slam(dataclasses.replace(drive.log, rgbd=rgbd), SlamConfig(particles=5),
                      rng=np.random.default_rng(0))

    assert result.texture is not None
    assert result.texture.colors.shape[:2] == result.grid.log_odds.shape
    assert (result.texture.resolution_m, result.texture.origin_x_m, result.texture.origin_y_m) == (
        result.grid.resolution_m, result.grid.origin_x_m, result.grid.origin_y_m)
    observed = int((result.texture.counts > 0).sum())
    assert observed > 5000
    assert result.input_summary["texture"] == f"texture from {observed} observed cells"
    placed, misplaced = colour_error(result, drive), colour_error(result, drive, shift_m=0.5)
    assert placed < 30.0 and placed < 0.7 * misplaced, (placed, misplaced)


def test_run_without_cameras_says_no_texture() -> None:
    drive = simulate("office", seed=0, rig="robot", max_duration_s=5)
    result = run_slam(drive.log, SlamConfig(particles=2), rng=np.random.default_rng(0))
    assert result.texture is None
    assert result.input_summary["texture"] == "no texture: the log has no camera data"
