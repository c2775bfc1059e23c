"""Motion models: odometry increments from wheel encoders / gyro, and the sampled odometry motion
model that moves particles (vectorised over steps or particles).

Increments are ``[dx_m, dy_m, dtheta_rad]`` in the vehicle frame at the start of a step, ready for
:func:`slam_engine.model.poses.compose`.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from slam_engine.model.poses import compose, relative, wrap_angle

STATIONARY_TRANS_M = 1e-6
STATIONARY_ROT_RAD = 1e-7


def wheel_distances_m(
    delta_ticks: np.ndarray, ticks_per_revolution: float, wheel_diameters_m: np.ndarray | tuple[float, ...]
) -> np.ndarray:
    """Travelled distance per wheel [m] from tick increments (M, n_wheels):
    ``ticks / ticks_per_revolution * pi * diameter`` with one diameter per wheel."""
    diameters = np.asarray(wheel_diameters_m, dtype=np.float64)
    return np.asarray(delta_ticks, dtype=np.float64) / float(ticks_per_revolution) * math.pi * diameters


def arc_increments(distance_m: np.ndarray, dtheta_rad: np.ndarray) -> np.ndarray:
    """(M, 3) increments for travelling ``distance_m`` along a circular arc while turning
    ``dtheta_rad`` (chord direction = half the turn)."""
    distance_m = np.asarray(distance_m, dtype=np.float64)
    dtheta_rad = np.asarray(dtheta_rad, dtype=np.float64)
    half = 0.5 * dtheta_rad
    # chord length of the arc: d * sin(h) / h (-> d as h -> 0)
    chord = distance_m * np.sinc(half / np.pi)
    return np.stack([chord * np.cos(half), chord * np.sin(half), dtheta_rad], axis=-1)


def differential_drive_increments(
    left_m: np.ndarray, right_m: np.ndarray, track_width_m: float, delta_yaw_rad: np.ndarray | None = None
) -> np.ndarray:
    """Differential drive: (M, 3) increments from left/right wheel distances [m]. The heading change
    is the gyro's ``delta_yaw_rad`` when given, else ``(right - left) / track_width_m``."""
    left_m = np.asarray(left_m, dtype=np.float64)
    right_m = np.asarray(right_m, dtype=np.float64)
    distance = 0.5 * (left_m + right_m)
    if delta_yaw_rad is None:
        if not track_width_m or track_width_m <= 0:
            raise ValueError("a differential drive without a gyro needs a positive track width")
        dtheta = (right_m - left_m) / float(track_width_m)
    else:
        dtheta = np.asarray(delta_yaw_rad, dtype=np.float64)
    return arc_increments(distance, dtheta)


def skid_steer_increments(
    wheels_m: np.ndarray, effective_track_width_m: float, delta_yaw_rad: np.ndarray | None = None
) -> np.ndarray:
    """Skid steer: (M, 3) increments from four wheel distances (M, 4) ordered FR, FL, RR, RL [m].
    Each side is the mean of its two wheels; the heading change is the IMU's ``delta_yaw_rad``
    (integrated, low-pass filtered yaw rate) when given, else the sides' difference over the
    *effective* track width (which absorbs the skidding)."""
    left, right = skid_steer_sides(wheels_m)
    return differential_drive_increments(left, right, effective_track_width_m, delta_yaw_rad)


def skid_steer_sides(wheels_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) side distances [m] of a skid steer: the mean of each side's two wheels
    from (..., 4) wheel distances ordered FR, FL, RR, RL."""
    wheels_m = np.asarray(wheels_m, dtype=np.float64)
    return 0.5 * (wheels_m[..., 1] + wheels_m[..., 3]), 0.5 * (wheels_m[..., 0] + wheels_m[..., 2])


def lowpass_alpha(dt_s: float, cutoff_hz: float | None) -> float:
    """Smoothing factor of a first-order low-pass filter for a sample ``dt_s`` after the last
    (1 = no filtering). ``y += alpha * (x - y)``."""
    if not cutoff_hz or cutoff_hz <= 0 or dt_s <= 0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt_s / (rc + dt_s)


def odometry_increments(odom_from: np.ndarray, odom_to: np.ndarray) -> np.ndarray:
    """(..., 3) ``[rot1_rad, trans_m, rot2_rad]`` between two odometry poses. Motion whose direction
    points backwards gets a negative ``trans`` (so reversing is not a half turn). For one pair of
    poses the (read-only) result is remembered: a filter step asks for the same pairs up to nine times."""
    odom_from = np.asarray(odom_from, dtype=np.float64)
    odom_to = np.asarray(odom_to, dtype=np.float64)
    if odom_from.shape == (3,) and odom_to.shape == (3,):
        return _pair_increments(odom_from.tobytes() + odom_to.tobytes())
    return _increments(odom_from, odom_to)


@functools.lru_cache(maxsize=16)
def _pair_increments(poses: bytes) -> np.ndarray:
    """:func:`odometry_increments` of one pair of poses, given as the bytes of their six float64 values."""
    pair = np.frombuffer(poses, np.float64).reshape(2, 3)
    increments = _increments(pair[0], pair[1])
    increments.flags.writeable = False
    return increments


def _increments(odom_from: np.ndarray, odom_to: np.ndarray) -> np.ndarray:
    """:func:`odometry_increments` of float64 arrays."""
    dx = odom_to[..., 0] - odom_from[..., 0]
    dy = odom_to[..., 1] - odom_from[..., 1]
    trans = np.hypot(dx, dy)
    direction = np.where(trans > STATIONARY_TRANS_M, np.arctan2(dy, dx), odom_from[..., 2])
    rot1 = wrap_angle(direction - odom_from[..., 2])
    backwards = np.abs(rot1) > 0.5 * np.pi
    rot1 = np.where(backwards, wrap_angle(rot1 + np.pi), rot1)
    trans = np.where(backwards, -trans, trans)
    rot2 = wrap_angle(odom_to[..., 2] - odom_from[..., 2] - rot1)
    return np.stack([rot1, trans, rot2], axis=-1)


def apply_odometry_increments(poses: np.ndarray, rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray) -> np.ndarray:
    """Move (N, 3) poses by rot1, trans, rot2 (each scalar or (N,))."""
    poses = np.asarray(poses, dtype=np.float64)
    heading = poses[..., 2] + rot1
    return np.stack(
        [poses[..., 0] + trans * np.cos(heading), poses[..., 1] + trans * np.sin(heading),
         wrap_angle(heading + rot2)],
        axis=-1,
    )


def _increment_sds(rot1: float, trans: float, rot2: float,
                   alphas: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """Standard deviations of rot1 [rad], trans [m] and rot2 [rad] in the rot1-trans-rot2 model."""
    a1, a2, a3, a4 = alphas
    abs_trans = abs(trans)
    return (a1 * abs(rot1) + a2 * abs_trans, a3 * abs_trans + a4 * (abs(rot1) + abs(rot2)),
            a1 * abs(rot2) + a2 * abs_trans)


def odometry_motion_sds(odom_from: np.ndarray, odom_to: np.ndarray,
                        alphas: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """Standard deviations ``(rot1 [rad], trans [m], rot2 [rad])`` of the motion ``odom_from -> odom_to``
    in the model of :func:`sample_odometry_motion`."""
    rot1, trans, rot2 = (float(v) for v in odometry_increments(odom_from, odom_to))
    return _increment_sds(rot1, trans, rot2, alphas)


def sample_odometry_motion(
    particles: np.ndarray,
    odom_from: np.ndarray,
    odom_to: np.ndarray,
    alphas: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> np.ndarray:
    """Sample new (N, 3) particle poses for the odometry step ``odom_from -> odom_to``
    (classic rot1-trans-rot2 model). ``alphas = (rot_from_rot, rot_from_trans, trans_from_trans,
    trans_from_rot)``: sd(rot) = a1 |rot| + a2 |trans|, sd(trans) = a3 |trans| + a4 (|rot1| + |rot2|).
    A stationary vehicle returns the particles unchanged: no motion, no noise."""
    particles = np.asarray(particles, dtype=np.float64)
    rot1, trans, rot2 = odometry_increments(odom_from, odom_to)
    if abs(trans) < STATIONARY_TRANS_M and abs(rot1) + abs(rot2) < STATIONARY_ROT_RAD:
        return particles.copy()
    n = particles.shape[0]
    sd_rot1, sd_trans, sd_rot2 = _increment_sds(rot1, trans, rot2, alphas)
    noise = rng.standard_normal((n, 3))
    return apply_odometry_increments(
        particles, rot1 + sd_rot1 * noise[:, 0], trans + sd_trans * noise[:, 1], rot2 + sd_rot2 * noise[:, 2]
    )


def odometry_motion_covariance(odom_from: np.ndarray, odom_to: np.ndarray,
                               alphas: tuple[float, float, float, float]) -> np.ndarray:
    """(3, 3) covariance of the motion ``odom_from -> odom_to`` as the rot1-trans-rot2 model of
    :func:`sample_odometry_motion` spreads it, in the frame of the start pose [m^2, m rad, rad^2]."""
    rot1, trans, rot2 = (float(v) for v in odometry_increments(odom_from, odom_to))
    sd = np.array(_increment_sds(rot1, trans, rot2, alphas))
    c, s = math.cos(rot1), math.sin(rot1)
    J = np.array([[-trans * s, c, 0.0], [trans * c, s, 0.0], [1.0, 0.0, 1.0]])  # d(dx, dy, dtheta)/d(rot1, trans, rot2)
    return J @ np.diag(sd**2) @ J.T


def propagate(pose: np.ndarray, odom_from: np.ndarray, odom_to: np.ndarray) -> np.ndarray:
    """Move ``pose`` by the odometry motion ``odom_from -> odom_to`` without noise."""
    return compose(pose, relative(odom_from, odom_to))
