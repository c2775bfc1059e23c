"""Render a textured flat floor (the world plane z = 0) into the images that calibrated cameras
would record: a stereo pair (raw: distorted, unrectified, Bayer-mosaiced when the calibration says
so) and a Kinect-style RGB-D frame (raw disparity in the THOR model + RGB).

Every pixel's ray is intersected with the floor (vectorised NumPy); ``floor_rgb(x_m, y_m)`` gives
the floor's colour at world points, (N,) arrays -> (N, 3) uint8. Rays that miss the floor (or hit
it beyond ``max_range_m``) see ``sky_rgb``. Poses are planar vehicle poses [x_m, y_m, theta_rad]
with the vehicle frame's origin on the floor.

    renderer = StereoRenderer(calibration)            # rays computed once
    left, right = renderer.render(floor_rgb, pose)
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from slam_engine.model.drive_log import RgbdCalibration, RgbdStream, StereoCalibration, StereoStream
from slam_engine.model.result import Trajectory
from slam_engine.texture.calibration import homogeneous
from slam_engine.texture.images import mosaic
from slam_engine.texture.rgbd import (
    KINECT_DD_OFFSET,
    KINECT_DD_PER_DISPARITY,
    KINECT_DEPTH_SCALE,
    KINECT_INVALID_DISPARITY,
    KINECT_RGB_DIVISOR,
    KINECT_RGB_SCALE,
    KINECT_RGB_SHIFT_PER_DD,
    KINECT_RGB_U_OFFSET,
    KINECT_RGB_V_OFFSET,
)

FloorRgb = Callable[[np.ndarray, np.ndarray], np.ndarray]
SKY_RGB = (170, 190, 220)


def floor_hits(origin: np.ndarray, directions: np.ndarray,
               max_range_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersections of rays with the plane z = 0: (N, 3) points [m], (N,) ray parameters s
    (point = origin + s * direction) and an (N,) bool mask of rays that hit within ``max_range_m``."""
    dz = directions[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -origin[2] / dz
    points = origin[None, :] + s[:, None] * directions
    distance = s * np.linalg.norm(directions, axis=1)
    hit = (dz < 0) & (s > 0) & (distance <= max_range_m)
    return points, s, hit


def _subpixel_offsets(supersample: int) -> np.ndarray:
    """(S*S, 2) sample offsets inside a pixel, centred on 0."""
    steps = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = np.meshgrid(steps, steps)
    return np.stack([du.ravel(), dv.ravel()], axis=-1)


def _pixel_grid(size_wh: tuple[int, int], du: float, dv: float) -> tuple[np.ndarray, np.ndarray]:
    w, h = size_wh
    v, u = np.mgrid[0:h, 0:w]
    return u.ravel() + du, v.ravel() + dv


def _pinhole_rays(u: np.ndarray, v: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(N, 3) ray directions (z = 1) in a pinhole camera's optical frame."""
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(u.size)], axis=-1)


def _distorted_rays(u: np.ndarray, v: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N, 3) ray directions (z = 1) of raw (distorted) pixels, undistorted with OpenCV."""
    pixels = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    normalized = cv2.undistortPoints(pixels, K, D, None, None, None, criteria).reshape(-1, 2)
    return np.concatenate([normalized, np.ones((len(normalized), 1))], axis=1)


class _Camera:
    """One camera on a vehicle driving on the floor. The vehicle moves in the plane, so where each
    pixel's ray meets the floor *in the vehicle frame* never changes: it is computed once, and a
    pose only moves those points into the world."""

    def __init__(self, size_wh: tuple[int, int], rays_camera: list[np.ndarray],
                 T_vehicle_from_camera: np.ndarray, max_range_m: float):
        self.size_wh = (int(size_wh[0]), int(size_wh[1]))
        R, origin = T_vehicle_from_camera[:3, :3], T_vehicle_from_camera[:3, 3]
        self.samples = []  # per sub-pixel sample: (hit mask (H*W,), hit points' vehicle xy (M, 2))
        for rays in rays_camera:
            points, _, hit = floor_hits(origin, rays @ R.T, max_range_m)
            self.samples.append((hit, points[hit, :2]))

    def render(self, floor_rgb: FloorRgb, pose: np.ndarray, sky_rgb: tuple[int, int, int]) -> np.ndarray:
        """(H, W, 3) uint8 image of the floor from the vehicle pose [x_m, y_m, theta_rad]."""
        x, y, theta = (float(v) for v in pose)
        c, s = np.cos(theta), np.sin(theta)
        total = np.zeros((self.size_wh[0] * self.size_wh[1], 3))
        for hit, xy_vehicle in self.samples:
            colors = np.empty_like(total)
            colors[:] = sky_rgb
            world_x = x + c * xy_vehicle[:, 0] - s * xy_vehicle[:, 1]
            world_y = y + s * xy_vehicle[:, 0] + c * xy_vehicle[:, 1]
            colors[hit] = np.asarray(floor_rgb(world_x, world_y), dtype=np.float64).reshape(-1, 3)
            total += colors
        w, h = self.size_wh
        return np.clip(np.rint(total / len(self.samples)), 0, 255).astype(np.uint8).reshape(h, w, 3)


class StereoRenderer:
    """Renders the raw (left, right) images of a calibrated stereo pair at planar vehicle poses.

    Pixels are undistorted with K and D; the right camera is placed by the rectification
    (``X_rect_left = X_rect_right + (baseline, 0, 0)``, ``X_rect = R @ X_cam``). Raw Bayer cameras
    get single-channel mosaiced frames, others (H, W, 3) RGB. ``supersample`` x ``supersample``
    rays per pixel are averaged (anti-aliasing, like a real lens's blur).
    """

    def __init__(self, calibration: StereoCalibration, supersample: int = 2, max_range_m: float = 80.0):
        cal = calibration
        self.calibration = cal
        offsets = _subpixel_offsets(supersample)
        R_left_from_rect = cal.R_left.T
        T_left_from_right = homogeneous(R_left_from_rect @ cal.R_right,
                                        R_left_from_rect @ np.array([cal.baseline_m, 0.0, 0.0]))
        self._cameras = [
            _Camera(cal.image_size_wh, [_distorted_rays(*_pixel_grid(cal.image_size_wh, du, dv), K, D)
                                        for du, dv in offsets], T, max_range_m)
            for K, D, T in ((cal.K_left, cal.D_left, cal.T_vehicle_from_camera),
                            (cal.K_right, cal.D_right, cal.T_vehicle_from_camera @ T_left_from_right))
        ]

    def render(self, floor_rgb: FloorRgb, pose: np.ndarray,
               sky_rgb: tuple[int, int, int] = SKY_RGB) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) raw frames at the vehicle pose [x_m, y_m, theta_rad]."""
        left, right = (camera.render(floor_rgb, pose, sky_rgb) for camera in self._cameras)
        pattern = self.calibration.bayer_pattern
        return (mosaic(left, pattern), mosaic(right, pattern)) if pattern else (left, right)


def kinect_rgb_pinhole(calibration: RgbdCalibration) -> tuple[float, float, float, float, float]:
    """The RGB camera implied by the THOR Kinect registration formulas: (fx, fy, cx, cy) [px] and
    its offset along the depth camera's x axis [m] (same orientation)."""
    scale = KINECT_RGB_SCALE / KINECT_RGB_DIVISOR
    return (scale * calibration.fx, scale * calibration.fy,
            (KINECT_RGB_SCALE * calibration.cx + KINECT_RGB_U_OFFSET) / KINECT_RGB_DIVISOR,
            (KINECT_RGB_SCALE * calibration.cy + KINECT_RGB_V_OFFSET) / KINECT_RGB_DIVISOR,
            -KINECT_RGB_SHIFT_PER_DD * KINECT_DEPTH_SCALE / (KINECT_RGB_SCALE * calibration.fx))


class KinectRenderer:
    """Renders THOR-model Kinect frames at planar vehicle poses: (raw disparity (H, W) uint16,
    RGB (H, W, 3) uint8).

    Disparity inverts ``depth = 1.03 / (-0.00304 d + 3.31)`` and is rounded to integers like the
    sensor's; pixels that see no floor within ``max_range_m`` get 2047 (no reading). The RGB image
    comes from the pinhole camera that the registration formulas imply (:func:`kinect_rgb_pinhole`).
    """

    def __init__(self, calibration: RgbdCalibration, rgb_size_wh: tuple[int, int] | None = None,
                 supersample: int = 2, max_range_m: float = 10.0):
        cal = calibration
        T = cal.T_vehicle_from_camera
        w, h = cal.image_size_wh
        depth_rays = _pinhole_rays(*_pixel_grid(cal.image_size_wh, 0.0, 0.0), cal.fx, cal.fy, cal.cx, cal.cy)
        _, depth_m, hit = floor_hits(T[:3, 3], depth_rays @ T[:3, :3].T, max_range_m)  # z = s: rays have z = 1
        disparity = np.full(len(depth_m), KINECT_INVALID_DISPARITY, dtype=np.float64)
        disparity[hit] = (KINECT_DEPTH_SCALE / depth_m[hit] - KINECT_DD_OFFSET) / KINECT_DD_PER_DISPARITY
        # On a flat floor the depth image is the same from every planar pose.
        self.disparity = np.clip(np.rint(disparity), 0, KINECT_INVALID_DISPARITY).astype(np.uint16).reshape(h, w)
        fx, fy, cx, cy, offset_m = kinect_rgb_pinhole(cal)
        size = rgb_size_wh or cal.image_size_wh
        self._rgb = _Camera(size, [_pinhole_rays(*_pixel_grid(size, du, dv), fx, fy, cx, cy)
                                   for du, dv in _subpixel_offsets(supersample)],
                            T @ homogeneous(np.eye(3), (offset_m, 0.0, 0.0)), max_range_m)

    def render(self, floor_rgb: FloorRgb, pose: np.ndarray,
               sky_rgb: tuple[int, int, int] = SKY_RGB) -> tuple[np.ndarray, np.ndarray]:
        """(disparity, rgb) at the vehicle pose [x_m, y_m, theta_rad]."""
        return self.disparity.copy(), self._rgb.render(floor_rgb, pose, sky_rgb)


def render_stereo_stream(floor_rgb: FloorRgb, trajectory: Trajectory, calibration: StereoCalibration,
                         supersample: int = 2, max_range_m: float = 80.0) -> StereoStream:
    """A :class:`StereoStream` with one rendered pair per pose of ``trajectory`` (images in memory)."""
    renderer = StereoRenderer(calibration, supersample, max_range_m)
    pairs = [renderer.render(floor_rgb, pose) for pose in trajectory.poses]
    return StereoStream(t_s=np.asarray(trajectory.t_s, dtype=np.float64), left_images=[p[0] for p in pairs],
                        right_images=[p[1] for p in pairs], calibration=calibration)


def render_rgbd_stream(floor_rgb: FloorRgb, trajectory: Trajectory, calibration: RgbdCalibration,
                       supersample: int = 2, max_range_m: float = 10.0) -> RgbdStream:
    """An :class:`RgbdStream` with one rendered disparity + RGB frame per pose (same timestamps)."""
    renderer = KinectRenderer(calibration, supersample=supersample, max_range_m=max_range_m)
    frames = [renderer.render(floor_rgb, pose) for pose in trajectory.poses]
    t_s = np.asarray(trajectory.t_s, dtype=np.float64)
    return RgbdStream(depth_t_s=t_s, depth_images=[f[0] for f in frames], rgb_t_s=t_s.copy(),
                      rgb_images=[f[1] for f in frames], calibration=calibration)
