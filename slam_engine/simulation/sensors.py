"""Sensor readings along a ground-truth motion, with realistic errors, from a seeded Generator.

Errors: each wheel has a constant scale error and a random slip on every increment; the gyro has a
constant bias, a slow bias random walk and white noise; LiDAR ranges get Gaussian noise and random
dropouts (no return).
"""

from __future__ import annotations

import numpy as np

from slam_engine.errors import ConfigError
from slam_engine.frontend.time_offset import beam_time_offsets_s
from slam_engine.model.drive_log import (
    EncoderStream,
    GyroStream,
    MotionModelKind,
    OdometryStream,
    ScanStream,
)
from slam_engine.model.poses import wrap_angle
from slam_engine.simulation.motion import Motion
from slam_engine.simulation.rigs import Rig
from slam_engine.simulation.world import World


def sample_times(motion: Motion, rate_hz: float, t0_s: float, rng: np.random.Generator,
                 jitter: float = 0.02) -> np.ndarray:
    """Sample stamps [s] at ``rate_hz`` over the motion with a small jitter, offset by ``t0_s``."""
    period = 1.0 / rate_hz
    t = np.arange(motion.t_s[0], motion.t_s[-1], period)
    t = t + rng.uniform(-jitter, jitter, t.size) * period
    t = np.clip(t, motion.t_s[0], motion.t_s[-1])
    return np.round(np.sort(t) + t0_s, 6)


def true_wheel_distances(motion: Motion, t_s: np.ndarray, rig: Rig) -> np.ndarray:
    """(N, n_wheels) cumulative tread distance [m] of each wheel, in the vehicle model's wheel order,
    from the exact motion (rolling without slip about the effective track)."""
    _, _, theta, s = motion.at(t_s)
    turn = (theta - motion.theta_rad[0]) * rig.true_track_m / 2
    left, right = s - turn, s + turn
    if rig.vehicle.kind == MotionModelKind.SKID_STEER:
        return np.column_stack([right, left, right, left])  # FR, FL, RR, RL
    return np.column_stack([left, right])


def measured_wheel_distances(true_m: np.ndarray, rig: Rig, rng: np.random.Generator) -> np.ndarray:
    """Cumulative distances as the encoders see them: scale error and random slip per increment."""
    steps = np.diff(true_m, axis=0, prepend=true_m[:1])
    scale = 1.0 + np.asarray(rig.wheel_scale_errors)[None, : true_m.shape[1]]
    slip = 1.0 + rig.slip_noise * rng.standard_normal(steps.shape)
    return np.cumsum(steps * scale * slip, axis=0)


def encoder_stream(motion: Motion, t_s: np.ndarray, rig: Rig, rng: np.random.Generator) -> EncoderStream:
    """Cumulative integer ticks (N, n_wheels) at ``t_s`` (absolute stamps)."""
    distances = measured_wheel_distances(true_wheel_distances(motion, t_s - rig.t0_s, rig), rig, rng)
    ticks_per_revolution = rig.vehicle.ticks_per_revolution
    if ticks_per_revolution is None:
        raise ConfigError(f"vehicle {rig.vehicle.name!r}: simulated encoders need ticks_per_revolution")
    per_tick = np.pi * np.asarray(rig.vehicle.wheel_diameters_m) / ticks_per_revolution
    ticks = np.floor(distances / per_tick[None, :]).astype(np.int64)
    return EncoderStream(t_s=t_s, ticks=ticks)


def gyro_stream(motion: Motion, t_s: np.ndarray, rig: Rig, rng: np.random.Generator) -> GyroStream:
    """Yaw rate [rad/s] with bias, bias random walk and white noise."""
    dt = np.diff(t_s, prepend=t_s[0])
    walk = np.cumsum(rng.standard_normal(t_s.size) * np.sqrt(dt)) * rig.gyro_bias_rad_s * 0.05
    rate = motion.yaw_rate_at(t_s - rig.t0_s) + rig.gyro_bias_rad_s + walk
    rate = rate + rig.gyro_noise_rad_s * rng.standard_normal(t_s.size)
    return GyroStream(t_s=t_s, yaw_rate_rad_s=rate)


def odometry_stream(motion: Motion, t_s: np.ndarray, rig: Rig, rng: np.random.Generator) -> OdometryStream:
    """Odometry poses dead-reckoned by the robot from its (erroneous, slipping) wheels."""
    two_wheel = rig.vehicle.kind != MotionModelKind.SKID_STEER
    true_m = true_wheel_distances(motion, t_s - rig.t0_s, rig)
    measured = measured_wheel_distances(true_m if two_wheel else true_m[:, [1, 0]], rig, rng)
    d_left, d_right = np.diff(measured, axis=0, prepend=measured[:1]).T
    d_centre = 0.5 * (d_left + d_right)
    heading = np.cumsum((d_right - d_left) / rig.true_track_m) + motion.theta_rad[0]
    mid = heading - 0.5 * (d_right - d_left) / rig.true_track_m
    x = motion.x_m[0] + np.cumsum(d_centre * np.cos(mid))
    y = motion.y_m[0] + np.cumsum(d_centre * np.sin(mid))
    return OdometryStream(t_s=t_s, poses=np.column_stack([x, y, wrap_angle(heading)]))


def scan_stream(world: World, motion: Motion, t_s: np.ndarray, rig: Rig, rng: np.random.Generator) -> ScanStream:
    """LiDAR ranges [m] (float32, inf = no return) cast in the world from the true poses at ``t_s``,
    the time of each scan's middle beam. A LiDAR model with a ``time_increment_s`` sweeps: each beam
    is cast from the pose at its own time (the scans are skewed as a real scanner's are). An interlaced
    rig's scans each start at their own angle (:meth:`Rig.scan_angle_offsets_rad`, carried in the stream)."""
    lidar = rig.lidar
    T = lidar.T_vehicle_from_lidar
    offsets = rig.scan_angle_offsets_rad(t_s.size)

    def beams_at(offset_rad: float) -> np.ndarray:
        angles = lidar.beam_angles_rad + offset_rad
        return (T[:3, :3] @ np.vstack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])).T

    beams_fixed = beams_at(0.0)
    x, y, theta, _ = motion.at(t_s - rig.t0_s)
    ranges = np.empty((t_s.size, lidar.num_beams), dtype=np.float32)
    sweep = beam_time_offsets_s(lidar.num_beams, lidar.time_increment_s)
    for k in range(t_s.size):
        beams_vehicle = beams_fixed if offsets is None else beams_at(float(offsets[k]))
        if sweep is not None:
            ranges[k] = _swept_scan(world, motion, t_s[k] - rig.t0_s + sweep, T, beams_vehicle, lidar.range_max_m)
            continue
        c, s = np.cos(theta[k]), np.sin(theta[k])
        R_world = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([x[k], y[k], 0.0]) + R_world @ T[:3, 3]
        ranges[k] = world.raycast(origin, beams_vehicle @ R_world.T, lidar.range_max_m)
    noisy = ranges + rig.range_noise_m * rng.standard_normal(ranges.shape).astype(np.float32)
    noisy[rng.random(ranges.shape) < rig.dropout_probability] = np.inf
    noisy[(noisy < lidar.range_min_m) | (noisy > lidar.range_max_m)] = np.inf
    return ScanStream(t_s=t_s, ranges_m=noisy, angle_offset_rad=offsets)


def _swept_scan(world: World, motion: Motion, beam_t_s: np.ndarray, T: np.ndarray, beams_vehicle: np.ndarray,
                max_range_m: float) -> np.ndarray:
    """One scan's ranges with each beam cast from the vehicle's pose at its time ``beam_t_s`` (B,)."""
    x, y, theta, _ = motion.at(beam_t_s)
    c, s = np.cos(theta), np.sin(theta)
    origins = np.column_stack([x + c * T[0, 3] - s * T[1, 3], y + s * T[0, 3] + c * T[1, 3],
                               np.full_like(x, T[2, 3])])
    directions = np.column_stack([c * beams_vehicle[:, 0] - s * beams_vehicle[:, 1],
                                  s * beams_vehicle[:, 0] + c * beams_vehicle[:, 1], beams_vehicle[:, 2]])
    return world.raycast(origins, directions, max_range_m)
