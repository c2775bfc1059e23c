"""RGB-D depth: the THOR/ECE276A Kinect v1 disparity model and its RGB registration, then the same
back-projection as stereo.

Kinect model (course spec; ``u`` = image column, ``v`` = row of the disparity image ``d``)::

    dd = -0.00304 * d + 3.31                     # inverse depth [1/m]
    depth = 1.03 / dd                            # [m]
    rgb_u = (526.37 * u + (-4.5 * 1750.46) * dd + 19276.0) / 585.051
    rgb_v = (526.37 * v + 16662.0) / 585.051

Equivalently the RGB camera is a pinhole with focal ``526.37 * f / 585.051`` px, the same
orientation as the depth camera and ``KINECT_RGB_OFFSET_M`` to its right (the IR-RGB baseline).

``model="depth_registered"``: depth images already in metres (float) or millimetres (uint16)
and registered pixel-for-pixel with the RGB images (as ROS ``depth_registered`` topics are).
"""

from __future__ import annotations

import numpy as np

from slam_engine.config import TextureConfig
from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import RgbdCalibration
from slam_engine.texture.images import to_uint8
from slam_engine.texture.stereo import FramePoints, back_project

KINECT_DD_PER_DISPARITY = -0.00304
KINECT_DD_OFFSET = 3.31
KINECT_DEPTH_SCALE = 1.03
KINECT_INVALID_DISPARITY = 2047
KINECT_RGB_SCALE = 526.37
KINECT_RGB_DIVISOR = 585.051
KINECT_RGB_SHIFT_PER_DD = -4.5 * 1750.46
KINECT_RGB_U_OFFSET = 19276.0
KINECT_RGB_V_OFFSET = 16662.0
KINECT_RGB_OFFSET_M = -KINECT_RGB_SHIFT_PER_DD * KINECT_DEPTH_SCALE / (KINECT_RGB_SCALE * KINECT_RGB_DIVISOR)

RGBD_MODELS = ("kinect_v1_thor", "depth_registered")


def kinect_inverse_depth(disparity: np.ndarray) -> np.ndarray:
    """``dd = -0.00304 * d + 3.31`` [1/m] of raw Kinect disparity values."""
    return KINECT_DD_PER_DISPARITY * np.asarray(disparity, dtype=np.float64) + KINECT_DD_OFFSET


def kinect_depth_m(disparity: np.ndarray) -> np.ndarray:
    """Depth ``1.03 / dd`` [m] of raw Kinect disparity; NaN for 0, 2047 (no reading) and dd <= 0."""
    d = np.asarray(disparity, dtype=np.float64)
    dd = kinect_inverse_depth(d)
    valid = (d > 0) & (d < KINECT_INVALID_DISPARITY) & (dd > 0)
    depth = np.full(d.shape, np.nan)
    depth[valid] = KINECT_DEPTH_SCALE / dd[valid]
    return depth


def kinect_rgb_pixel(u: np.ndarray, v: np.ndarray, dd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(column, row) in the RGB image [px, float] of disparity pixel (u, v) with inverse depth dd."""
    rgb_u = (KINECT_RGB_SCALE * u + KINECT_RGB_SHIFT_PER_DD * dd + KINECT_RGB_U_OFFSET) / KINECT_RGB_DIVISOR
    rgb_v = (KINECT_RGB_SCALE * v + KINECT_RGB_V_OFFSET) / KINECT_RGB_DIVISOR
    return rgb_u, rgb_v


def rgbd_frame_points(depth_image: np.ndarray, rgb_image: np.ndarray, calibration: RgbdCalibration,
                      config: TextureConfig, what: str = "rgbd frame") -> FramePoints:
    """Coloured 3-D points of one depth/disparity frame and its RGB frame within the configured
    depth range, in the depth camera's optical frame."""
    if depth_image.ndim != 2:
        raise LogFormatError(f"depth image of shape {depth_image.shape}, expected (H, W)", None, what)
    if calibration.model == "kinect_v1_thor":
        depth = kinect_depth_m(depth_image)
    elif calibration.model == "depth_registered":
        depth = depth_image.astype(np.float64) * (1e-3 if np.issubdtype(depth_image.dtype, np.integer) else 1.0)
        depth[~(depth > 0)] = np.nan
    else:
        raise LogFormatError(f"unknown RGB-D model {calibration.model!r}, expected one of {RGBD_MODELS}",
                             None, "rgbd.calibration.model")
    keep = (depth >= config.min_depth_m) & (depth <= min(config.max_depth_m, config.rgbd_max_depth_m))
    v, u = np.nonzero(keep)
    if calibration.model == "kinect_v1_thor":
        rgb_u, rgb_v = kinect_rgb_pixel(u, v, KINECT_DEPTH_SCALE / depth[v, u])
        rgb_u, rgb_v = np.rint(rgb_u).astype(np.int64), np.rint(rgb_v).astype(np.int64)
    else:
        rgb_u, rgb_v = u, v
    h, w = rgb_image.shape[:2]
    inside = (rgb_u >= 0) & (rgb_u < w) & (rgb_v >= 0) & (rgb_v < h)
    u, v, rgb_u, rgb_v = u[inside], v[inside], rgb_u[inside], rgb_v[inside]
    points = back_project(depth, calibration.fx, calibration.fy, calibration.cx, calibration.cy)
    return FramePoints(points_camera=points[v, u], colors=to_uint8(rgb_image)[rgb_v, rgb_u],
                       T_vehicle_from_camera=calibration.T_vehicle_from_camera)
