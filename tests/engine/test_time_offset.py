"""The LiDAR-to-odometry time offset: estimated from matched turns (synthetic steps and a simulated
rover whose scans lag its wheel ticks by a known 0.15 s), left at zero without an offset, and scan
de-skew (a swept scan of a straight wall comes out straight)."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.config import SlamConfig, validate_config
from slam_engine.errors import ConfigError
from slam_engine.evaluation.metrics import absolute_trajectory_error
from slam_engine.frontend.lidar_points import ScanProjector
from slam_engine.frontend.time_offset import (
    OdometryHistory,
    TimeOffsetEstimator,
    beam_time_offsets_s,
    matched_turn,
    sweep_poses,
)
from slam_engine.model.drive_log import LidarModel
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate
from slam_engine.simulation.motion import Motion
from slam_engine.simulation.world import World


def _turning_heading(t: np.ndarray) -> np.ndarray:
    """A heading that turns left and right at up to ~1.2 rad/s (turn rates that change often)."""
    return 0.6 * np.sin(1.3 * t) + 0.4 * np.sin(0.47 * t + 1.0) + 0.05 * t


def _feed(estimator: TimeOffsetEstimator, true_offset_s: float, seconds: float, noise_rad: float,
          rng: np.random.Generator) -> OdometryHistory:
    """Odometry at 50 Hz along :func:`_turning_heading`; a processed scan every 0.2 s whose matched turn
    is the true turn between the instants stamp + true_offset (plus noise)."""
    history = OdometryHistory(keep_s=2.0)
    t_odom = np.arange(0.0, seconds, 0.02)
    scans = list(np.arange(1.0, seconds - 1.0, 0.2))
    previous = None
    for t in t_odom:
        history.append(t, np.array([0.1 * t, 0.0, _turning_heading(np.array([t]))[0]]))
        while scans and scans[0] <= t:
            stamp = scans.pop(0)
            turn = None
            if previous is not None:
                turn = float(_turning_heading(np.array([stamp + true_offset_s]))[0]
                             - _turning_heading(np.array([previous + true_offset_s]))[0]) + rng.normal(0, noise_rad)
            estimator.record_step(stamp, turn)
            previous = stamp
        estimator.update(history)
    estimator.update(history, final=True)
    return history


@pytest.mark.parametrize("true_offset_s", [-0.15, 0.08])
def test_estimator_recovers_a_known_offset_from_matched_turns(true_offset_s: float) -> None:
    estimator = TimeOffsetEstimator()
    _feed(estimator, true_offset_s, 60.0, noise_rad=0.01, rng=np.random.default_rng(0))
    assert estimator.estimate_s == pytest.approx(true_offset_s, abs=0.01)  # standard error 4 ms
    assert estimator.applied_s == pytest.approx(true_offset_s, abs=0.0125)  # on the 5 ms grid
    summary = estimator.summary()
    assert summary["confident"] and summary["mode"] == "auto" and summary["steps_used"] > 200


def test_without_an_offset_nothing_is_applied_and_a_fixed_offset_always_is() -> None:
    estimator = TimeOffsetEstimator()
    _feed(estimator, 0.0, 60.0, noise_rad=0.01, rng=np.random.default_rng(1))
    assert abs(estimator.estimate_s) < 0.005
    assert estimator.applied_s == 0.0 and estimator.applied_changes == 0
    fixed = TimeOffsetEstimator(fixed_s=-0.1)
    assert fixed.applied_s == -0.1
    _feed(fixed, -0.2, 30.0, noise_rad=0.01, rng=np.random.default_rng(2))
    assert fixed.applied_s == -0.1  # the configured offset is used ...
    assert fixed.summary()["estimated_s"] == pytest.approx(-0.2, abs=0.01)  # ... and the estimate reported


def test_noisy_matches_without_turns_give_no_offset() -> None:
    """Matched turns that carry no information about the offset (pure noise, large) never get applied."""
    estimator = TimeOffsetEstimator()
    history = OdometryHistory(keep_s=2.0)
    rng = np.random.default_rng(3)
    for k in range(2000):
        t = 0.05 * k
        history.append(t, np.array([0.05 * t, 0.0, 0.0]))
        if k % 4 == 0:
            estimator.record_step(t, float(rng.normal(0, 0.05)))
        estimator.update(history)
    assert estimator.applied_s == 0.0


def test_odometry_history_interpolates_unwrapped_and_keeps_a_window() -> None:
    history = OdometryHistory(keep_s=1.0)
    for k in range(40):
        history.append(0.1 * k, np.array([float(k), 0.0, np.angle(np.exp(1j * 0.3 * k))]))  # heading wraps
    assert len(history) <= 13
    pose = history.pose_at(3.55)
    assert pose[0] == pytest.approx(35.5)
    assert pose[2] == pytest.approx(np.angle(np.exp(1j * 0.3 * 35.5)))  # along the short arc
    assert history.headings_at(np.array([3.9]))[0] - history.headings_at(np.array([3.0]))[0] == pytest.approx(2.7)
    assert history.covers(3.5) and not history.covers(1.0)


def test_matched_turn_needs_most_matches_accepted() -> None:
    before = np.zeros((4, 3))
    after = np.zeros((4, 3))
    after[:, 2] = [0.1, 0.12, 0.5, 0.5]
    assert matched_turn(before, after, np.array([True, True, False, False])) == pytest.approx(0.11)
    assert matched_turn(before, after, np.array([True, False, False, False])) is None


def test_deskew_straightens_a_wall_swept_during_a_fast_turn() -> None:
    """A URG-04LX-like scanner (67 ms sweep) turning at 2 rad/s in front of a wall 2 m ahead: the raw
    end points bend by centimetres, the de-skewed ones lie on the wall."""
    n, increment = 241, np.radians(0.5)
    lidar = LidarModel(num_beams=n, angle_min_rad=-(n - 1) / 2 * increment, angle_increment_rad=increment,
                       range_min_m=0.02, range_max_m=5.6, time_increment_s=0.0667 / (n - 1))
    world = World("wall", np.array([[2.0, -10.0, 2.0, 10.0]]), np.zeros((2, 2)), 2.0, 1.0)
    t = np.linspace(0.0, 1.0, 1001)
    motion = Motion(t_s=t, x_m=np.zeros_like(t), y_m=np.zeros_like(t), theta_rad=2.0 * (t - 0.5), s_m=np.zeros_like(t))
    offsets = beam_time_offsets_s(n, lidar.time_increment_s)
    assert offsets is not None and offsets[-1] - offsets[0] == pytest.approx(0.0667)
    x, y, theta, _ = motion.at(0.5 + offsets)
    directions = np.column_stack([np.cos(theta + lidar.beam_angles_rad), np.sin(theta + lidar.beam_angles_rad),
                                  np.zeros(n)])
    origins = np.column_stack([x, y, np.full(n, 0.5)])
    ranges = world.raycast(origins, directions, 5.6)
    history = OdometryHistory(keep_s=5.0)
    for k in range(len(t)):
        history.append(t[k], np.array([0.0, 0.0, theta_at(motion, t[k])]))
    projector = ScanProjector(lidar, 30.0, -1.0, 10.0, 0.05)
    raw = projector.project(ranges)
    deskewed = projector.project(ranges, sweep_poses(history, 0.5, offsets))
    raw_error = np.abs(raw.hits_v[:, 0] - 2.0).max()
    deskewed_error = np.abs(deskewed.hits_v[:, 0] - 2.0).max()
    assert raw_error > 0.03
    assert deskewed_error < 0.002


def theta_at(motion: Motion, t: float) -> float:
    return float(np.interp(t, motion.t_s, motion.theta_rad))


def test_config_time_offset_is_auto_or_a_bounded_number() -> None:
    assert SlamConfig().odometry.time_offset_s == "auto"
    assert validate_config({"odometry": {"time_offset_s": -0.15}}).odometry.time_offset_s == -0.15
    for bad in (1.5, "later"):
        with pytest.raises(ConfigError, match="time_offset_s"):
            validate_config({"odometry": {"time_offset_s": bad}})


@pytest.mark.slow
def test_simulated_rover_whose_scans_lag_its_ticks_by_150_ms() -> None:
    """The Mines rover (BreezySLAM's robot, URG-04LX sweeping its beams) with scans stamped 0.15 s after
    they were measured: the estimate lands within 20 ms of -0.15 s, is applied, and the map is as
    accurate as without the lag; the same drive without a lag gets no offset."""
    lagged = simulate("office", seed=0, rig="mines-rover", max_duration_s=45.0, cameras=False, scan_lag_s=0.15)
    result = run_slam(lagged.log, SlamConfig(particles=10, seed=0))
    summary = result.input_summary["time_offset"]
    # measured: estimated -0.158 s (standard error 7 ms, evidence 450), applied -0.16 s, ATE 0.009 m vs 0.38 m
    # dead reckoning (the simulated office turns at most 0.9 rad/s: the matcher absorbs the lag there too)
    assert summary["estimated_s"] == pytest.approx(-0.15, abs=0.02)
    assert summary["applied_s"] == pytest.approx(-0.15, abs=0.02)
    assert summary["deskew"] and summary["sweep_s"] == pytest.approx(0.0665, abs=1e-3)
    ate = absolute_trajectory_error(result.trajectory, lagged.ground_truth)
    assert ate < 0.05
    assert ate * 5 < absolute_trajectory_error(result.dead_reckoning, lagged.ground_truth)

    plain = simulate("office", seed=0, rig="mines-rover", max_duration_s=45.0, cameras=False)
    summary = run_slam(plain.log, SlamConfig(particles=10, seed=0)).input_summary["time_offset"]
    assert abs(summary["estimated_s"]) < 0.03  # measured 0.014 s (standard error 8 ms, evidence 4)
    assert summary["applied_s"] == 0.0 and not summary["confident"]


def test_simulated_lag_stamps_scans_late_and_keeps_the_truth_at_the_measurement() -> None:
    plain = simulate("office", seed=0, rig="mines-rover", max_duration_s=5.0, cameras=False)
    lagged = simulate("office", seed=0, rig="mines-rover", max_duration_s=5.0, cameras=False, scan_lag_s=0.15)
    np.testing.assert_allclose(lagged.log.scans.t_s, plain.log.scans.t_s + 0.15, atol=1e-6)
    np.testing.assert_array_equal(lagged.log.scans.ranges_m, plain.log.scans.ranges_m)
    np.testing.assert_allclose(lagged.ground_truth.poses, plain.ground_truth.poses)
    np.testing.assert_allclose(lagged.log.encoders.t_s, lagged.log.scans.t_s)  # ticks read at the stamps
