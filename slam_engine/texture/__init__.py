"""Ground texture maps from stereo and RGB-D cameras, built once the trajectory is known.

Each used camera frame is turned into coloured 3-D points (stereo: rectify + SGBM; RGB-D: the
Kinect disparity model), placed in the world with the trajectory interpolated at the frame's time,
cut to the ground band and binned into the occupancy grid's cells::

    texture = build_texture_map(log, result.trajectory, result.grid, config)  # None: no cameras
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from slam_engine.config import SlamConfig, TextureConfig
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.poses import to_matrix_4x4
from slam_engine.model.result import OccupancyGrid, TextureMap, Trajectory
from slam_engine.texture.images import read_frame
from slam_engine.texture.projection import (
    estimate_ground_z,
    ground_mask,
    interpolate_poses,
    transform_points,
)
from slam_engine.texture.rgbd import rgbd_frame_points
from slam_engine.texture.stereo import FramePoints, GroundWindow, StereoRectifier, stereo_frame_points
from slam_engine.texture.texture_map import TextureAccumulator

__all__ = ["build_texture_map", "TextureAccumulator", "FramePoints"]

GROUND_SAMPLE_FRAMES = 5


@dataclass
class _CameraSource:
    """One camera stream: frame times [s] and ``frame_points(i, ground_z_m)``, frame i's points (None =
    unusable), matched only where ground at ``ground_z_m`` [m] can be seen (None: the whole image)."""

    name: str
    t_s: np.ndarray
    frame_points: Callable[[int, float | None], FramePoints | None]


def build_texture_map(log: DriveLog, trajectory: Trajectory, grid: OccupancyGrid,
                      config: SlamConfig | TextureConfig | None = None,
                      warnings: list[str] | None = None) -> TextureMap | None:
    """Ground texture on ``grid``'s geometry from the log's stereo and/or RGB-D frames.

    ``trajectory`` gives the vehicle's map-frame poses (e.g. ``SlamResult.trajectory``); frames
    outside its time span (plus ``max_time_gap_s``) are skipped. Returns None when the log has no
    camera data, texturing is disabled, or no frame could be used; notes such as the estimated
    ground height or points outside the grid are appended to ``warnings`` when given.
    """
    cfg = config.texture if isinstance(config, SlamConfig) else (config or TextureConfig())
    notes = warnings if warnings is not None else []
    sources = _camera_sources(log, cfg)
    if not cfg.enabled or not sources or len(trajectory) == 0:
        return None

    selected = []
    for source in sources:
        indices = _select_frames(source.t_s, trajectory, cfg)
        if len(source.t_s) and not len(indices):
            notes.append(f"texture: no {source.name} frame lies within the trajectory's time span")
        selected.append((source, indices))
    if not any(len(indices) for _, indices in selected):
        return None

    cache: dict[tuple[str, int], FramePoints | None] = {}
    ground_z_m = cfg.ground_z_m
    if ground_z_m is None:
        ground_z_m = _estimate_ground(selected, cache)
        if ground_z_m is None:
            ground_z_m = 0.0
            notes.append("texture: no ground plane found in the camera points; assuming ground at z = 0 m")
        else:
            notes.append(f"texture: ground estimated at z = {ground_z_m:.3f} m in the vehicle frame")

    accumulator: TextureAccumulator | None = None
    frames_used = 0
    for t_s, frame in _frames(selected, cache, ground_z_m):
        if frame is None or len(frame.points_camera) == 0:
            continue
        pose, _ = interpolate_poses(trajectory, np.array([t_s]), cfg.max_time_gap_s)
        T_world_from_camera = to_matrix_4x4(pose[0]) @ frame.T_vehicle_from_camera
        points_world = transform_points(frame.points_camera, T_world_from_camera)
        on_ground = ground_mask(points_world, ground_z_m, cfg.ground_band_m)
        if accumulator is None:
            accumulator = TextureAccumulator(grid, 3 if frame.colors.ndim == 2 else 1, cfg.cell_mode)
        accumulator.add(points_world[on_ground, 0], points_world[on_ground, 1], frame.colors[on_ground])
        frames_used += 1
    if accumulator is None:
        notes.append("texture: no camera frame gave usable depth")
        return None
    if accumulator.points_outside:
        share = accumulator.points_outside / max(1, accumulator.points_outside + accumulator.points_added)
        notes.append(f"texture: {share:.1%} of ground points fell outside the occupancy grid and were dropped")
    notes.append(f"texture: {frames_used} camera frames used")
    return accumulator.texture_map()


def _camera_sources(log: DriveLog, cfg: TextureConfig) -> list[_CameraSource]:
    sources = []
    if log.stereo is not None and len(log.stereo):
        stereo = log.stereo
        rectifier = StereoRectifier(stereo.calibration)

        windows: dict[float, GroundWindow | None] = {}

        def stereo_points(i: int, ground_z_m: float | None) -> FramePoints:
            what = f"stereo frame {i}"
            left = read_frame(stereo.left_images[i], what + " (left)")
            right = read_frame(stereo.right_images[i], what + " (right)")
            window = None
            if ground_z_m is not None:
                if ground_z_m not in windows:
                    windows[ground_z_m] = rectifier.ground_window(ground_z_m, cfg)
                window = windows[ground_z_m]
            return stereo_frame_points(left, right, rectifier, cfg, what, window)

        sources.append(_CameraSource("stereo", np.asarray(stereo.t_s, dtype=np.float64), stereo_points))
    if log.rgbd is not None and len(log.rgbd) and len(log.rgbd.rgb_t_s):
        rgbd = log.rgbd
        rgb_t = np.asarray(rgbd.rgb_t_s, dtype=np.float64)

        def rgbd_points(i: int, ground_z_m: float | None) -> FramePoints | None:
            t = float(rgbd.depth_t_s[i])
            j = int(np.clip(np.searchsorted(rgb_t, t), 1, len(rgb_t) - 1)) if len(rgb_t) > 1 else 0
            if len(rgb_t) > 1 and abs(rgb_t[j - 1] - t) <= abs(rgb_t[j] - t):
                j -= 1
            if abs(rgb_t[j] - t) > cfg.max_time_gap_s:
                return None
            depth = read_frame(rgbd.depth_images[i], f"rgbd depth frame {i}")
            rgb = read_frame(rgbd.rgb_images[j], f"rgbd rgb frame {j}")
            return rgbd_frame_points(depth, rgb, rgbd.calibration, cfg, f"rgbd depth frame {i}")

        sources.append(_CameraSource("rgbd", np.asarray(rgbd.depth_t_s, dtype=np.float64), rgbd_points))
    return sources


def _select_frames(t_s: np.ndarray, trajectory: Trajectory, cfg: TextureConfig) -> np.ndarray:
    """Indices of the frames to use: every ``frame_stride``-th frame within the trajectory's span,
    thinned evenly to at most ``max_frames``."""
    indices = np.arange(len(t_s))[:: cfg.frame_stride]
    _, valid = interpolate_poses(trajectory, t_s[indices], cfg.max_time_gap_s)
    indices = indices[valid]
    if len(indices) > cfg.max_frames:
        indices = indices[np.unique(np.linspace(0, len(indices) - 1, cfg.max_frames).round().astype(np.int64))]
    return indices


def _estimate_ground(selected: list, cache: dict) -> float | None:
    """Ground height [m] from a few evenly spread frames' points in the vehicle frame."""
    points = []
    for source, indices in selected:
        picks = indices[np.unique(np.linspace(0, len(indices) - 1, min(GROUND_SAMPLE_FRAMES, len(indices)))
                                  .round().astype(np.int64))] if len(indices) else []
        for i in picks:
            frame = cache.setdefault((source.name, int(i)), source.frame_points(int(i), None))
            if frame is not None and len(frame.points_camera):
                points.append(transform_points(frame.points_camera, frame.T_vehicle_from_camera))
    return estimate_ground_z(np.concatenate(points)) if points else None


def _frames(selected: list, cache: dict, ground_z_m: float) -> Iterator[tuple[float, FramePoints | None]]:
    """(time [s], points) of every selected frame, in stream order, reusing cached frames; the others
    computed where they can see ground at ``ground_z_m`` [m]."""
    for source, indices in selected:
        for i in indices:
            key = (source.name, int(i))
            frame = cache.pop(key) if key in cache else source.frame_points(int(i), ground_z_m)
            yield float(source.t_s[i]), frame
