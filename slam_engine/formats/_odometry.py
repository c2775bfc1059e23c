"""Odometry helpers for format conversion: wheel dead reckoning, pose interpolation, SE(2)/SE(3) bits.

The SLAM engine has its own motion models; these exist so that a log with wheel encoders can be
written in a format that stores odometry poses (CARMEN, ROS Odometry), and for loader tests.
"""

from __future__ import annotations

import numpy as np

from slam_engine.drive_log import DriveLog, MotionModelKind, OdometryStream, VehicleModel
from slam_engine.errors import LogFormatError


def wrap_angle(theta_rad: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(theta_rad) + np.pi) % (2 * np.pi) - np.pi


def wheel_distances_m(vehicle: VehicleModel, ticks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative (left, right) travelled distance [m] from (N, n_wheels) cumulative ticks.

    Skid-steer: left = mean(front_left, rear_left), right = mean(front_right, rear_right).
    """
    if vehicle.ticks_per_revolution is None or not vehicle.wheel_diameters_m:
        raise LogFormatError("vehicle model lacks ticks_per_revolution or wheel_diameters_m")
    names = list(vehicle.wheel_names)
    diameters = np.broadcast_to(np.asarray(vehicle.wheel_diameters_m, dtype=np.float64), (len(names),))
    metres = ticks.astype(np.float64) * (np.pi * diameters / vehicle.ticks_per_revolution)
    columns = {name: metres[:, k] for k, name in enumerate(names)}
    if vehicle.kind == MotionModelKind.SKID_STEER:
        left = 0.5 * (columns["front_left"] + columns["rear_left"])
        right = 0.5 * (columns["front_right"] + columns["rear_right"])
    else:
        left, right = columns["left"], columns["right"]
    return left, right


def dead_reckon(log: DriveLog) -> OdometryStream:
    """Odometry poses at the encoder stamps: wheel distances for translation, heading from the
    gyro's integrated yaw rate when there is a gyro, else from the wheel difference and track."""
    if log.odometry is not None:
        return log.odometry
    if log.encoders is None or len(log.encoders) == 0:
        raise LogFormatError("log has neither odometry poses nor wheel encoders")
    t = np.asarray(log.encoders.t_s, dtype=np.float64)
    left, right = wheel_distances_m(log.vehicle, log.encoders.ticks)
    d_centre = np.diff(0.5 * (left + right), prepend=0.5 * (left[0] + right[0]))
    if log.gyro is not None and len(log.gyro) > 1:
        heading = integrate_yaw_rate(log.gyro.t_s, log.gyro.yaw_rate_rad_s, t)
    else:
        if not log.vehicle.track_width_m:
            raise LogFormatError("vehicle model lacks track_width_m and the log has no gyro")
        heading = (right - left - (right[0] - left[0])) / log.vehicle.track_width_m
    mid_heading = heading - 0.5 * np.diff(heading, prepend=heading[0])
    x = np.cumsum(d_centre * np.cos(mid_heading))
    y = np.cumsum(d_centre * np.sin(mid_heading))
    return OdometryStream(t_s=t, poses=np.column_stack([x, y, wrap_angle(heading)]))


def integrate_yaw_rate(t_s: np.ndarray, yaw_rate_rad_s: np.ndarray, at_t_s: np.ndarray) -> np.ndarray:
    """Heading [rad] (unwrapped, 0 at the first gyro sample) at ``at_t_s``, trapezoidal integration."""
    t_s = np.asarray(t_s, dtype=np.float64)
    rate = np.asarray(yaw_rate_rad_s, dtype=np.float64)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t_s))])
    return np.interp(at_t_s, t_s, heading)


def interpolate_poses(t_s: np.ndarray, poses: np.ndarray, at_t_s: np.ndarray) -> np.ndarray:
    """(M, 3) poses at ``at_t_s``, linear in x, y and unwrapped theta (held at the ends)."""
    theta = np.unwrap(poses[:, 2])
    return np.column_stack([
        np.interp(at_t_s, t_s, poses[:, 0]),
        np.interp(at_t_s, t_s, poses[:, 1]),
        wrap_angle(np.interp(at_t_s, t_s, theta)),
    ])


def se2_matrix(x: float, y: float, theta: float) -> np.ndarray:
    """4x4 transform of a planar pose (z = 0, rotation about z)."""
    T = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x, y
    return T


def planar_part(T: np.ndarray) -> tuple[float, float, float] | None:
    """(x, y, yaw) of a 4x4 transform whose rotation is about z only; None when it is tilted."""
    R = np.asarray(T)[:3, :3]
    if abs(R[2, 2] - 1.0) > 1e-6:
        return None
    return float(T[0, 3]), float(T[1, 3]), float(np.arctan2(R[1, 0], R[0, 0]))


def compose_se2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) poses a ⊕ b (b expressed in a's frame)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1],
                            a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            wrap_angle(a[:, 2] + b[:, 2])])


def relative_se2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) poses of b expressed in a's frame (a^-1 ⊕ b)."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[:, 2])])
