"""Systematic heading error added to a log's odometry, to check that mapping survives it.

``true turn`` becomes ``scale * turn + drift_rad_per_m * signed distance`` between consecutive
odometry poses (Borenstein's UMBmark errors: a wrong track width scales every turn, unequal wheel
diameters bend every metre). Logged odometry poses (CARMEN) are re-integrated with the error;
wheel-encoder logs get the equivalent vehicle model (track width / scale; drift needs poses).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from slam_engine.model.drive_log import DriveLog, OdometryStream
from slam_engine.model.poses import compose, relative


def with_heading_error(log: DriveLog, scale: float, drift_rad_per_m: float = 0.0) -> DriveLog:
    """``log`` with its odometry's heading error changed by ``scale`` and ``drift_rad_per_m``."""
    if log.odometry is not None and len(log.odometry):
        poses = np.asarray(log.odometry.poses, dtype=np.float64)
        steps = relative(poses[:-1], poses[1:])
        forward = np.sign(steps[:, 0]) * np.hypot(steps[:, 0], steps[:, 1])
        steps[:, 2] = scale * steps[:, 2] + drift_rad_per_m * forward
        out = np.empty_like(poses)
        out[0] = poses[0]
        for i, step in enumerate(steps):
            out[i + 1] = compose(out[i], step)
        return dataclasses.replace(log, odometry=OdometryStream(log.odometry.t_s, out))
    if log.vehicle is not None and log.vehicle.track_width_m and drift_rad_per_m == 0.0:
        vehicle = dataclasses.replace(log.vehicle, track_width_m=log.vehicle.track_width_m / scale)
        return dataclasses.replace(log, vehicle=vehicle)
    raise ValueError("heading error: the log needs logged odometry poses (or encoders, scale only)")
