"""Odometry smoothing: the noise of matches and odometry measured from a path, and smoothing that
keeps precise odometry's local precision without moving the path where odometry is the worse source."""

from __future__ import annotations

import numpy as np

from slam_engine.backend.odometry_smoothing import smooth_with_odometry
from slam_engine.frontend.odometry_noise import OdometryPrecision, estimate_noise, wheel_distance_sd_m
from slam_engine.model.poses import compose, relative, wrap_angle


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


def _observed(fitted: np.ndarray, odo: np.ndarray) -> OdometryPrecision:
    """An OdometryPrecision that has seen every step of ``fitted`` poses against ``odo`` (a model of
    5 cm and 0.05 rad per step)."""
    precision = OdometryPrecision()
    for k in range(len(fitted)):
        precision.observe(fitted[k], odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    return precision


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
    precision = _observed(truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.01, 0.01, 0.002]), odo)
    assert precision.estimate is not None and not precision.trusted
    assert precision.scaled((0.1, 0.05, 0.05, 0.02)) == (0.1, 0.05, 0.05, 0.02)


def _wheels_and_gyro(truth: np.ndarray, sd_side_m: float, track_m: float, rng: np.random.Generator) -> np.ndarray:
    """(K, 3) cumulative left, right side distances [m] (independent noise sd_side_m per step) and
    the gyro's yaw [rad] (exact) along ``truth``, the sides turning about an effective ``track_m``."""
    steps = relative(truth[:-1], truth[1:])
    distance, turn = np.hypot(steps[:, 0], steps[:, 1]), steps[:, 2]
    left = distance - 0.5 * track_m * turn + rng.normal(0.0, sd_side_m, len(steps))
    right = distance + 0.5 * track_m * turn + rng.normal(0.0, sd_side_m, len(steps))
    cumulative = np.column_stack([np.cumsum(left), np.cumsum(right), np.cumsum(turn)])
    return np.vstack([np.zeros(3), cumulative])


def test_wheels_checked_against_the_gyro_give_their_distance_noise() -> None:
    rng = np.random.default_rng(5)
    truth = _drive()
    # 1.4 mm per side and step: the travelled distance (the sides' mean) carries 1 mm
    for track_m in (1.5, 2.2):  # a skid steer turns about a wider effective track: it is fitted
        sd = wheel_distance_sd_m(_wheels_and_gyro(truth, 0.0014, track_m, rng))
        assert sd is not None and 0.0008 < sd < 0.0012
    assert wheel_distance_sd_m(_wheels_and_gyro(truth[:20], 0.0014, 1.5, rng)) is None  # too short to tell


def test_wheel_check_caps_the_odometry_noise_where_the_front_end_drifts() -> None:
    """Matches that each carry the last step's error (a street: the scans constrain the travel
    direction weakly) drift like odometry; the differences alone blame the odometry for it."""
    rng = np.random.default_rng(6)
    truth = _drive()
    odo = _odometry(truth, 0.001, 0.0002, rng)
    drift = np.cumsum(rng.normal(0.0, 0.006, len(truth)))  # 6 mm per step along the travel direction
    matched = truth.copy()
    matched[:, 0] += drift * np.cos(truth[:, 2])
    matched[:, 1] += drift * np.sin(truth[:, 2])
    blind = estimate_noise(matched, odo)
    assert blind is not None and blind.odometry_sd_m > 0.004 and blind.wheel_sd_m is None
    checked = estimate_noise(matched, odo, _wheels_and_gyro(truth, 0.0014, 1.5, rng))
    assert checked is not None and checked.wheel_sd_m is not None
    assert 0.0008 < checked.odometry_sd_m < 0.0012 and checked.odometry_sd_m == checked.wheel_sd_m
    assert checked.summary()["wheel_sd_m_per_step"] == round(checked.wheel_sd_m, 5)


def test_front_end_does_not_trust_odometry_only_marginally_more_precise() -> None:
    """Matches of 1.2 mm against odometry of 1 mm per step: smoothing may use it, the proposal not."""
    rng = np.random.default_rng(7)
    truth = _drive(150)
    odo = _odometry(truth, 0.001, 0.0002, rng)
    precision = _observed(truth + rng.normal(0.0, 1.0, truth.shape) * np.array([0.0012, 0.0012, 0.0003]), odo)
    assert precision.estimate is not None and precision.estimate.odometry_helps
    assert not precision.estimate.more_precise_by(2.0) and not precision.trusted


def test_front_end_keeps_trusting_odometry_while_it_stays_the_more_precise_source() -> None:
    """Trust starts at twice the matches' precision and ends only where the odometry is no longer the
    more precise source: windows where the match noise dips close to the odometry's (a drifting front
    end's white part falls to the floor) do not switch the proposal back and forth."""
    rng = np.random.default_rng(8)
    truth = _drive(900)
    steps = relative(truth[:-1], truth[1:])
    sd = np.where(np.arange(len(steps))[:, None] < 600, [0.001, 0.001, 0.0002], [0.05, 0.05, 0.03])
    odo = np.zeros_like(truth)  # 1 mm / 0.0002 rad per step, rough (5 cm, 0.03 rad) from step 600
    for k, step in enumerate(steps + rng.normal(0.0, 1.0, steps.shape) * sd):
        odo[k + 1] = compose(odo[k], step)
    precision = OdometryPrecision()
    for k in range(300):  # matches of 2 cm: trusted
        fitted = truth[k] + rng.normal(0.0, 1.0, 3) * np.array([0.02, 0.02, 0.002])
        precision.observe(fitted, odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    assert precision.trusted and precision.changes == 1
    for k in range(300, 600):  # matches of 1.2 mm against odometry of 1 mm: kept
        fitted = truth[k] + rng.normal(0.0, 1.0, 3) * np.array([0.0012, 0.0012, 0.0003])
        precision.observe(fitted, odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    assert precision.estimate is not None and not precision.estimate.more_precise_by(2.0)
    assert precision.trusted and precision.changes == 1
    for k in range(600, 900):  # rough odometry: no longer trusted
        fitted = truth[k] + rng.normal(0.0, 1.0, 3) * np.array([0.0012, 0.0012, 0.0003])
        precision.observe(fitted, odo[k], model_sd_m=0.05, model_sd_rad=0.05)
    assert not precision.trusted and precision.changes == 2
