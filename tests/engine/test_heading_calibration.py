"""Online heading calibration: recovers a turn scale and a drift per metre from matched turns,
corrects nothing inside its dead band, and leaves the motion alone when disabled."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.frontend.heading_calibration import HeadingCalibration
from slam_engine.frontend.motion_models import apply_odometry_increments


def _feed(cal: HeadingCalibration, scale: float, drift: float, steps: int, rng: np.random.Generator) -> None:
    """Steps of 0.2 m with odometry turns of +-0.15 rad; the true turn has the given error plus
    matching noise (sd 0.005 rad) on 30 particles."""
    for _ in range(steps):
        odom_turn = rng.uniform(-0.15, 0.15)
        trans = rng.choice([0.2, -0.1])
        odom_from = np.array([1.0, 2.0, 0.3])
        odom_to = apply_odometry_increments(odom_from, odom_turn / 2, trans, odom_turn / 2)
        before = np.zeros((30, 3))
        after = before.copy()
        after[:, 2] = scale * odom_turn + drift * trans + rng.normal(0.0, 0.005, 30)
        cal.observe(odom_from, odom_to, before, after, np.ones(30, bool))


def test_recovers_turn_scale_and_drift_per_metre() -> None:
    cal = HeadingCalibration(prior_scale_rad2=0.5, prior_drift_m2=10.0)
    _feed(cal, scale=0.625, drift=-0.03, steps=5000, rng=np.random.default_rng(0))  # prior shrinkage ~0.005
    assert cal.scale == pytest.approx(0.625, abs=0.01)
    assert cal.drift_rad_per_m == pytest.approx(-0.03, abs=0.004)
    assert (cal.applied_scale, cal.applied_drift_rad_per_m) == (cal.scale, cal.drift_rad_per_m)
    # the corrected odometry turns like the truth: 0.1 rad of odometry and 0.2 m -> 0.0565 rad
    target = cal.corrected_target(np.zeros(3), apply_odometry_increments(np.zeros(3), 0.05, 0.2, 0.05))
    assert target[2] == pytest.approx(0.625 * 0.1 - 0.03 * 0.2, abs=0.002)


def test_small_errors_stay_inside_the_dead_band_and_correct_nothing() -> None:
    cal = HeadingCalibration(prior_scale_rad2=0.5, prior_drift_m2=10.0, scale_band=0.1, drift_band_rad_per_m=0.01)
    _feed(cal, scale=0.95, drift=0.003, steps=1000, rng=np.random.default_rng(1))
    assert cal.scale == pytest.approx(0.95, abs=0.01)  # measured ...
    assert (cal.applied_scale, cal.applied_drift_rad_per_m) == (1.0, 0.0)  # ... but not applied
    odom_to = np.array([0.3, 0.1, 0.2])
    np.testing.assert_array_equal(cal.corrected_target(np.zeros(3), odom_to), odom_to)


def test_disabled_or_mostly_rejected_steps_leave_the_estimate_at_identity() -> None:
    off = HeadingCalibration(prior_scale_rad2=0.5, prior_drift_m2=10.0, enabled=False)
    _feed(off, scale=0.6, drift=0.05, steps=200, rng=np.random.default_rng(2))
    assert (off.scale, off.drift_rad_per_m, off.steps_used) == (1.0, 0.0, 0)
    cal = HeadingCalibration(prior_scale_rad2=0.5, prior_drift_m2=10.0)
    accepted = np.zeros(30, bool)
    accepted[:10] = True  # a third of the matches accepted: the step is not trusted
    cal.observe(np.zeros(3), np.array([0.2, 0.0, 0.1]), np.zeros((30, 3)), np.full((30, 3), 0.5), accepted)
    assert cal.steps_used == 0 and cal.scale == 1.0
