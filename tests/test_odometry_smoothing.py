"""Odometry smoothing: the noise of matches and odometry measured from a path, and smoothing that
keeps precise odometry's local precision without moving the path where odometry is the worse source."""

from __future__ import annotations

import numpy as np

from slam_engine.backend.odometry_smoothing import smooth_with_odometry
from slam_engine.odometry_noise import OdometryPrecision, estimate_noise
from slam_engine.poses import compose, relative, wrap_angle


def _drive(n: int = 400) -> np.ndarray:
    """A smooth drive of n key frames 1 m apart, bending slowly left and right."""
    poses = np.zeros((n, 3))
    for k in range(1, n):
        poses[k] = compose(poses[k - 1], np.array([1.0, 0.0, 0.05 * np.sin(k / 15.0)]))
    return poses


def _odometry(truth: np.ndarray, sd_m: float, sd_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Dead reckoning from the true steps with white noise of sd_m / sd_rad per step."""
    steps = relative(truth[:-1], truth[1:])
    steps += rng.normal(0.0, 1.0, steps.shape) * np.array([sd_m, sd_m, sd_rad])
    odo = np.zeros_like(truth)
    for k, s in enumerate(steps):
        odo[k + 1] = compose(odo[k], s)
    return odo


def _local_error_m(poses: np.ndarray, truth: np.ndarray) -> float:
    e, t = relative(poses[:-1], poses[1:]), relative(truth[:-1], truth[1:])
    return float(np.mean(np.hypot(e[:, 0] - t[:, 0], e[:, 1] - t[:, 1])))


def test_precise_odometry_takes_over_locally_and_matches_keep_the_global_shape() -> None:
    rng = np.random.default_rng(1)
    truth = _drive()
    odo = _odometry(truth, 0.001, 0.0002, rng)  # fibre-optic-gyro grade: 1 mm, 0.01 deg per step
    matched = truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.02, 0.02, 0.002])  # 2 cm match noise
    matched[:, 2] = wrap_angle(matched[:, 2])
    noise = estimate_noise(matched, odo)
    assert noise is not None and noise.odometry_helps
    assert 0.01 < noise.match_sd_m < 0.03 and noise.odometry_sd_m < 0.005
    assert 0.001 < noise.match_sd_rad < 0.003 and noise.odometry_sd_rad < 0.001
    smoothed = smooth_with_odometry(matched, odo, noise)
    before, after = _local_error_m(matched, truth), _local_error_m(smoothed, truth)
    assert before > 0.02 and after < 0.25 * before
    # globally it stays with the matches: no odometry drift comes in
    assert np.abs(smoothed[:, :2] - truth[:, :2]).max() < 0.05


def test_rough_odometry_is_not_trusted() -> None:
    rng = np.random.default_rng(2)
    truth = _drive()
    odo = _odometry(truth, 0.05, 0.03, rng)  # wheels on a rough floor: 5 cm, 1.7 deg per step
    matched = truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.01, 0.01, 0.002])
    noise = estimate_noise(matched, odo)
    assert noise is not None and not noise.odometry_helps


def test_short_drives_are_left_alone() -> None:
    truth = _drive(20)
    assert estimate_noise(truth, truth) is None


def test_front_end_trusts_precise_odometry_and_scales_its_motion_model() -> None:
    rng = np.random.default_rng(3)
    truth = _drive(150)
    odo = _odometry(truth, 0.001, 0.0002, rng)
    fitted = truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.02, 0.02, 0.002])
    precision = OdometryPrecision(every_steps=25, window_steps=200)
    assert precision.scaled((0.1, 0.05, 0.05, 0.02)) == (0.1, 0.05, 0.05, 0.02)  # the model until measured
    for k in range(len(truth)):
        precision.observe(fitted[k], odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    assert precision.trusted and precision.changes == 1
    # measured: about 1 mm and 0.0002 rad per step against the model's 5 cm and 0.05 rad
    assert 0.02 <= precision.trans_scale < 0.15 and 0.02 <= precision.rot_scale < 0.02 * 1.5
    a1, a2, a3, a4 = precision.scaled((0.1, 0.05, 0.05, 0.02))
    assert a1 == 0.1 * precision.rot_scale and a3 == 0.05 * precision.trans_scale
    assert precision.summary()["trusted"] is True


def test_front_end_keeps_its_motion_model_for_rough_odometry() -> None:
    rng = np.random.default_rng(4)
    truth = _drive(150)
    odo = _odometry(truth, 0.05, 0.03, rng)
    fitted = truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.01, 0.01, 0.002])
    precision = OdometryPrecision()
    for k in range(len(truth)):
        precision.observe(fitted[k], odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    assert precision.estimate is not None and not precision.trusted
    assert precision.scaled((0.1, 0.05, 0.05, 0.02)) == (0.1, 0.05, 0.05, 0.02)
