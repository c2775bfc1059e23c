"""Ground truth by simulation: a known floor texture rendered into stereo pairs (the ECE276A car's
real calibration, raw Bayer frames) and Kinect frames (THOR model) along a known path; the texture
map built from them must reproduce the floor, cell for cell."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from slam_engine.config import SlamConfig, TextureConfig
from slam_engine.model.drive_log import DriveLog, MotionModelKind, VehicleModel
from slam_engine.model.result import OccupancyGrid, Trajectory
from slam_engine.simulation.camera_render import KinectRenderer, render_rgbd_stream, render_stereo_stream
from slam_engine.texture import build_texture_map
from slam_engine.texture.calibration import load_ece276a_stereo_calibration, thor_kinect_calibration
from slam_engine.texture.rgbd import kinect_depth_m

PALETTE = np.array([[200, 60, 40], [40, 160, 60], [50, 70, 200], [220, 200, 60]], dtype=np.float64)


def square_index(x_m: np.ndarray, y_m: np.ndarray, square_m: float) -> np.ndarray:
    """Palette index of the floor square under (x, y): neighbours always differ."""
    ix = np.floor(np.asarray(x_m) / square_m).astype(np.int64)
    iy = np.floor(np.asarray(y_m) / square_m).astype(np.int64)
    return (ix + 2 * iy) % len(PALETTE)


def make_floor(square_m: float, grain_amplitude: float):
    """Coloured squares plus a fixed pseudo-random 5 cm grain (stereo needs texture to match)."""

    def floor_rgb(x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        a = np.floor(x_m / 0.05).astype(np.int64)
        b = np.floor(y_m / 0.05).astype(np.int64)
        grain = (((a * 73856093) ^ (b * 19349663)) % 1009) / 1008.0 - 0.5
        rgb = PALETTE[square_index(x_m, y_m, square_m)] + grain_amplitude * grain[:, None]
        return np.clip(rgb, 0, 255).astype(np.uint8)

    return floor_rgb


def path(t_s: np.ndarray, speed_m_s: float) -> np.ndarray:
    """Known poses [x, y, theta] along a gently turning path, linear in time (so linear
    interpolation between poses is exact)."""
    return np.stack([speed_m_s * t_s, 0.1 * speed_m_s * t_s, 0.06 * t_s], axis=-1)


def truth_colors(texture, grid: OccupancyGrid, floor_rgb, cells: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Mean floor colour over each given cell (8 x 8 samples)."""
    iy, ix = cells
    x, y = grid.cell_to_world(ix, iy)
    offsets = ((np.arange(8) + 0.5) / 8 - 0.5) * grid.resolution_m
    sx = (x[:, None, None] + offsets[None, :, None] + 0 * offsets[None, None, :]).ravel()
    sy = (y[:, None, None] + 0 * offsets[None, :, None] + offsets[None, None, :]).ravel()
    return floor_rgb(sx, sy).astype(np.float64).reshape(len(x), 64, 3).mean(axis=1)


def placement(texture, grid: OccupancyGrid, square_m: float, cells) -> tuple[float, float]:
    """(share of observed cells whose colour is nearest their square's palette colour, largest
    distance of a wrong cell's centre from a square edge [cells])."""
    iy, ix = cells
    x, y = grid.cell_to_world(ix, iy)
    got = texture.colors[iy, ix].astype(np.float64)
    nearest = np.argmin(((got[:, None, :] - PALETTE[None]) ** 2).sum(axis=-1), axis=1)
    right = nearest == square_index(x, y, square_m)
    fx, fy = (x / square_m) % 1.0, (y / square_m) % 1.0
    edge_distance = np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy)) * square_m / grid.resolution_m
    return float(right.mean()), float(edge_distance[~right].max()) if (~right).any() else 0.0


def vehicle() -> VehicleModel:
    return VehicleModel(kind=MotionModelKind.DIFFERENTIAL)


@functools.cache
def stereo_drive(param_dir: str):
    """Two raw stereo pairs of a 1 m checkerboard, 1.5 m apart, with the car's calibration
    (rendered once per test session)."""
    calibration = load_ece276a_stereo_calibration(param_dir)
    floor_rgb = make_floor(1.0, 40.0)
    camera_t = np.array([0.25, 0.75])
    stream = render_stereo_stream(floor_rgb, Trajectory(camera_t, path(camera_t, 3.0)), calibration)
    trajectory_t = np.arange(0.0, 1.01, 0.1)  # poses at other times than the images
    return stream, Trajectory(trajectory_t, path(trajectory_t, 3.0)), floor_rgb


def test_stereo_texture_matches_the_floor(dataset):
    stream, trajectory, floor_rgb = stereo_drive(str(dataset("ece276a-car/param")))
    grid = OccupancyGrid(np.zeros((100, 100)), 0.2, -2.0, -10.0)
    notes: list[str] = []
    texture = build_texture_map(DriveLog(vehicle(), stereo=stream), trajectory, grid, SlamConfig(), notes)
    assert texture.colors.shape == (100, 100, 3)  # Bayer camera: colour texture
    assert (texture.resolution_m, texture.origin_x_m, texture.origin_y_m) == (0.2, -2.0, -10.0)
    observed = np.nonzero(texture.counts > 0)
    assert len(observed[0]) > 1500  # measured 2061 cells (82 m^2); 2091 matching the full width
    error = np.abs(texture.colors[observed].astype(np.float64) - truth_colors(texture, grid, floor_rgb, observed))
    assert error.mean() < 12.0  # measured 9.3 (of 255); 8.3 matching the full width
    share_right, worst_edge_distance = placement(texture, grid, 1.0, observed)
    assert share_right > 0.96  # measured 0.978
    assert worst_edge_distance <= 1.5 + 1e-9  # wrong cells touch an edge cell: placement within one cell
    assert any("ground estimated at z = " in note for note in notes)


def test_gray_stereo_gives_a_gray_texture(dataset):
    stream, trajectory, floor_rgb = stereo_drive(str(dataset("ece276a-car/param")))
    to_gray = np.array([0.299, 0.587, 0.114])
    gray_stream = dataclasses.replace(
        stream,
        left_images=[_demosaic_gray(img) for img in stream.left_images],
        right_images=[_demosaic_gray(img) for img in stream.right_images],
        calibration=dataclasses.replace(stream.calibration, bayer_pattern=None),
    )
    grid = OccupancyGrid(np.zeros((100, 100)), 0.2, -2.0, -10.0)
    texture = build_texture_map(DriveLog(vehicle(), stereo=gray_stream), trajectory, grid,
                                TextureConfig(ground_z_m=0.0))
    assert texture.colors.shape == (100, 100)
    observed = np.nonzero(texture.counts > 0)
    truth = truth_colors(texture, grid, floor_rgb, observed) @ to_gray
    assert np.abs(texture.colors[observed] - truth).mean() < 10.0


def _demosaic_gray(raw: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(cv2.cvtColor(raw, cv2.COLOR_BAYER_BG2RGB), cv2.COLOR_RGB2GRAY)


def test_kinect_renderer_inverts_the_thor_disparity_model():
    calibration = thor_kinect_calibration()
    floor_rgb = make_floor(0.25, 0.0)
    disparity, rgb = KinectRenderer(calibration, supersample=1).render(floor_rgb, np.zeros(3))
    assert disparity.dtype == np.uint16 and disparity.shape == (480, 640) and rgb.shape == (480, 640, 3)
    # The centre pixel looks 0.36 rad down from 0.36 m: it sees the floor at 0.36 / sin(0.36) m.
    depth = kinect_depth_m(disparity[240:246, 313:319])
    assert np.nanmedian(depth) == pytest.approx(0.36 / np.sin(0.36), rel=0.01)
    assert (disparity[0] == 2047).all()  # the top rows look above the floor's 10 m horizon


@pytest.mark.parametrize("cell_mode", ["mean", "latest"])
def test_rgbd_texture_matches_the_floor(cell_mode):
    calibration = thor_kinect_calibration()
    floor_rgb = make_floor(0.25, 0.0)
    camera_t = np.arange(0.0, 2.51, 0.5)
    stream = render_rgbd_stream(floor_rgb, Trajectory(camera_t, path(camera_t, 0.3)), calibration)
    trajectory_t = np.arange(-0.1, 2.65, 0.125)
    trajectory = Trajectory(trajectory_t, path(trajectory_t, 0.3))
    grid = OccupancyGrid(np.zeros((120, 160)), 0.05, -1.0, -3.0)
    config = SlamConfig(texture=TextureConfig(cell_mode=cell_mode))
    texture = build_texture_map(DriveLog(vehicle(), rgbd=stream), trajectory, grid, config)
    observed = np.nonzero(texture.counts > 0)
    assert len(observed[0]) > 4000  # measured 5217 cells (13.0 m^2)
    error = np.abs(texture.colors[observed].astype(np.float64) - truth_colors(texture, grid, floor_rgb, observed))
    assert error.mean() < 9.0  # measured 7.1 (mean), 6.2 (latest); Kinect depth steps are 5 cm at 4 m
    share_right, worst_edge_distance = placement(texture, grid, 0.25, observed)
    assert share_right > (0.97 if cell_mode == "mean" else 0.95)  # measured 0.983 (mean), 0.963 (latest)
    assert worst_edge_distance <= 1.5 + 1e-9


def test_no_camera_data_gives_no_texture():
    grid = OccupancyGrid(np.zeros((10, 10)), 0.1, 0.0, 0.0)
    trajectory = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)))
    assert build_texture_map(DriveLog(vehicle()), trajectory, grid, SlamConfig()) is None


def test_frames_outside_the_trajectory_are_skipped_and_reported():
    calibration = thor_kinect_calibration()
    camera_t = np.array([10.0, 11.0])
    stream = render_rgbd_stream(make_floor(0.25, 0.0), Trajectory(camera_t, path(camera_t, 0.3)), calibration,
                                supersample=1)
    trajectory = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)))
    notes: list[str] = []
    grid = OccupancyGrid(np.zeros((10, 10)), 0.1, 0.0, 0.0)
    assert build_texture_map(DriveLog(vehicle(), rgbd=stream), trajectory, grid, SlamConfig(), notes) is None
    assert notes == ["texture: no rgbd frame lies within the trajectory's time span"]
