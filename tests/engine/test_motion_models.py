"""Motion models against hand-computed cases; the sampled odometry model's noise; dead reckoning."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_engine.errors import ConfigError
from slam_engine.frontend.motion_models import (
    differential_drive_increments,
    odometry_increments,
    sample_odometry_motion,
    skid_steer_increments,
    wheel_distances_m,
)
from slam_engine.frontend.odometry import dead_reckoning
from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    MotionModelKind,
    OdometryStream,
    VehicleModel,
)

ALPHAS = (0.1, 0.05, 0.05, 0.02)


def test_ticks_to_metres_per_wheel_diameter() -> None:
    # 100 ticks per revolution: 50 ticks are half a circumference pi * d / 2
    d = wheel_distances_m(np.array([[50, 100]]), 100, (0.2, 0.3))
    np.testing.assert_allclose(d, [[math.pi * 0.1, math.pi * 0.3]])


def test_differential_drive_straight_and_turn_in_place() -> None:
    np.testing.assert_allclose(differential_drive_increments([1.0], [1.0], 0.5), [[1.0, 0.0, 0.0]], atol=1e-12)
    # wheels in opposite directions: turn (r - l) / track = 0.4 rad on the spot
    np.testing.assert_allclose(differential_drive_increments([-0.1], [0.1], 0.5), [[0.0, 0.0, 0.4]], atol=1e-12)


def test_differential_drive_quarter_circle() -> None:
    # track 1 m, left 0.5 pi/2, right 1.5 pi/2: a quarter circle of radius 1 m around (0, 1)
    inc = differential_drive_increments([0.25 * math.pi], [0.75 * math.pi], 1.0)
    np.testing.assert_allclose(inc, [[1.0, 1.0, math.pi / 2]], atol=1e-12)


def test_gyro_yaw_replaces_wheel_heading() -> None:
    inc = differential_drive_increments([1.0], [1.2], 0.5, delta_yaw_rad=np.array([0.0]))
    np.testing.assert_allclose(inc, [[1.1, 0.0, 0.0]], atol=1e-12)


def test_skid_steer_averages_each_side() -> None:
    # FR, FL, RR, RL: right side 0.3 m, left side 0.1 m, effective track 0.8 m
    inc = skid_steer_increments(np.array([[0.35, 0.05, 0.25, 0.15]]), 0.8)
    dtheta = 0.2 / 0.8
    chord = 0.2 * math.sin(dtheta / 2) / (dtheta / 2)
    np.testing.assert_allclose(inc, [[chord * math.cos(dtheta / 2), chord * math.sin(dtheta / 2), dtheta]])


def test_odometry_increments_reverse_is_negative_translation() -> None:
    rot1, trans, rot2 = odometry_increments(np.array([0.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.1]))
    assert abs(rot1) < 1e-12 and abs(trans + 1.0) < 1e-12 and abs(rot2 - 0.1) < 1e-12


def test_stationary_vehicle_neither_moves_nor_spreads() -> None:
    particles = np.tile([1.0, 2.0, 0.3], (50, 1))
    odom = np.array([5.0, 5.0, 1.0])
    out = sample_odometry_motion(particles, odom, odom.copy(), ALPHAS, np.random.default_rng(0))
    np.testing.assert_array_equal(out, particles)


def test_sampled_motion_spread_matches_the_model() -> None:
    n = 20000
    particles = np.zeros((n, 3))
    out = sample_odometry_motion(particles, np.zeros(3), np.array([1.0, 0.0, 0.0]), ALPHAS,
                                 np.random.default_rng(0))
    # pure 1 m translation: sd(trans) = 0.05, sd(rot1) = sd(rot2) = 0.05 -> sd(theta) = 0.05 * sqrt(2)
    assert abs(out[:, 0].mean() - 1.0) < 0.002
    assert abs(out[:, 0].std() - 0.05) < 0.003
    assert abs(out[:, 2].std() - 0.05 * math.sqrt(2)) < 0.003
    assert abs(out[:, 1].std() - 0.05) < 0.003  # lateral spread from rot1 at 1 m


def _vehicle(kind: MotionModelKind = MotionModelKind.DIFFERENTIAL) -> VehicleModel:
    return VehicleModel(kind=kind, ticks_per_revolution=100, wheel_diameters_m=(1 / math.pi, 1 / math.pi),
                        wheel_names=("left", "right"), track_width_m=0.5)


def test_dead_reckoning_from_encoders_square_turn() -> None:
    # 1 tick = 1 cm. Drive 1 m, turn 90 deg left on the spot (right +pi/4*0.5 m), drive 1 m.
    quarter = 39  # ticks per wheel for about 90 deg at track 0.5 m (0.39 m of arc)
    ticks = np.array([[0, 0], [100, 100], [100 - quarter, 100 + quarter], [200 - quarter, 200 + quarter]])
    log = DriveLog(vehicle=_vehicle(), encoders=EncoderStream(t_s=np.arange(4.0), ticks=ticks))
    dr = dead_reckoning(log)
    turn = 2 * quarter / 100 / 0.5
    np.testing.assert_allclose(dr.poses[1], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(dr.poses[3], [1.0 + math.cos(turn), math.sin(turn), turn], atol=1e-9)


def test_dead_reckoning_heading_from_gyro_when_present() -> None:
    # wheels say "straight", the gyro says 0.5 rad/s for 1 s: heading follows the gyro
    ticks = np.array([[0, 0], [100, 100]])
    log = DriveLog(vehicle=_vehicle(), encoders=EncoderStream(t_s=np.array([0.0, 1.0]), ticks=ticks),
                   gyro=GyroStream(t_s=np.array([0.0, 0.5]), yaw_rate_rad_s=np.array([0.5, 0.5])))
    dr = dead_reckoning(log)
    np.testing.assert_allclose(dr.poses[-1, 2], 0.5, atol=1e-9)
    np.testing.assert_allclose(dr.poses[-1, :2], [math.cos(0.25) * math.sin(0.25) / 0.25,
                                                  math.sin(0.25) * math.sin(0.25) / 0.25], atol=1e-9)


def test_dead_reckoning_of_logged_odometry_starts_at_origin() -> None:
    poses = np.array([[5.0, 5.0, np.pi / 2], [5.0, 6.0, np.pi / 2]])
    log = DriveLog(vehicle=VehicleModel(kind=MotionModelKind.ODOMETRY),
                   odometry=OdometryStream(t_s=np.array([0.0, 1.0]), poses=poses))
    np.testing.assert_allclose(dead_reckoning(log).poses, [[0, 0, 0], [1.0, 0.0, 0.0]], atol=1e-12)


def test_missing_calibration_and_missing_odometry_are_config_errors() -> None:
    log = DriveLog(vehicle=VehicleModel(kind=MotionModelKind.DIFFERENTIAL),
                   encoders=EncoderStream(t_s=np.arange(2.0), ticks=np.zeros((2, 2), np.int64)))
    with pytest.raises(ConfigError, match="ticks_per_revolution"):
        dead_reckoning(log)
    with pytest.raises(ConfigError, match="no odometry source"):
        dead_reckoning(DriveLog(vehicle=_vehicle()))


def test_increments_of_one_pair_equal_the_batched_ones_and_are_not_mixed_up() -> None:
    """One pair's increments are remembered (a filter step asks for the same pairs repeatedly): each
    pair still gets its own, the same values as computing them in a batch, and they cannot be altered."""
    rng = np.random.default_rng(4)
    starts = rng.uniform(-5, 5, (50, 3))
    ends = starts + rng.normal(0, 0.3, (50, 3))
    ends[::7] = starts[::7]  # standing still
    batched = odometry_increments(starts, ends)
    for _ in range(2):  # the second pass reads what the first remembered
        for start, end, expected in zip(starts, ends, batched, strict=True):
            got = odometry_increments(start, end)
            np.testing.assert_array_equal(got, expected)
            assert not got.flags.writeable
    # a pose changed in place after a call gives the new pose's increments
    pose = np.zeros(3)
    first = odometry_increments(np.zeros(3), pose).copy()
    pose[0] = 1.0
    assert odometry_increments(np.zeros(3), pose)[1] == 1.0 and first[1] == 0.0
