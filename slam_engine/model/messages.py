"""Single sensor messages: what :meth:`DriveLog.messages` yields and what a streaming filter steps on.

Units: seconds, metres, radians. The service's streamed chunks carry the same fields
(``api_schemas`` mirrors them as JSON).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EncoderMessage:
    """Cumulative wheel ticks, one per wheel in the vehicle model's ``wheel_names`` order."""

    t_s: float
    ticks: np.ndarray


@dataclass(frozen=True)
class GyroMessage:
    """Yaw rate about the vehicle's z axis [rad/s]."""

    t_s: float
    yaw_rate_rad_s: float


@dataclass(frozen=True)
class OdometryMessage:
    """A logged odometry pose in the odometry frame [m, m, rad]."""

    t_s: float
    x_m: float
    y_m: float
    theta_rad: float


@dataclass(frozen=True)
class ScanMessage:
    """One LiDAR scan: ranges [m] in the log's :class:`LidarModel` beam order; inf = no return.
    ``angle_offset_rad``: this scan's beams point ``angle_offset_rad`` further counter-clockwise than
    the model's (a laser whose start angle changes from scan to scan, e.g. an interlaced SICK)."""

    t_s: float
    ranges_m: np.ndarray
    angle_offset_rad: float = 0.0


@dataclass(frozen=True)
class StereoMessage:
    """One stereo pair: file paths or arrays."""

    t_s: float
    left: str | np.ndarray
    right: str | np.ndarray


@dataclass(frozen=True)
class RgbdMessage:
    """One depth/disparity frame (RGB frames are matched by timestamp)."""

    t_s: float
    depth: str | np.ndarray


Message = EncoderMessage | GyroMessage | OdometryMessage | ScanMessage | StereoMessage | RgbdMessage
