"""The particle weight's motion prior: a fit far out in the predicted motion's spread weighs little;
one near the prediction, or off it only where the scan leaves the pose open, costs nothing."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.motion_models import odometry_motion_covariance
from slam_engine.frontend.particle_filter import fit_surprise, world_motion_information


def _one_metre_ahead(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n particles at the origin heading along x, a 1 m straight motion with the default model's
    spread (heading sd about 0.07 rad), and the predicted poses."""
    particles = np.zeros((n, 3))
    alphas = (0.1, 0.05, 0.05, 0.02)  # the default MotionNoiseConfig: rot/rot, rot/trans, trans/trans, trans/rot
    cov = odometry_motion_covariance(np.zeros(3), np.array([1.0, 0.0, 0.0]), alphas)
    predicted = np.tile([1.0, 0.0, 0.0], (n, 1))
    return particles, world_motion_information(particles, cov), predicted


def test_a_fit_far_out_in_the_motions_tail_is_surprising() -> None:
    particles, info_motion, predicted = _one_metre_ahead(3)
    info_fit = np.tile(np.diag([4e4, 4e4, 4e4]), (3, 1, 1))  # a sharp fit: about 5 mm / 5 mrad
    fitted = predicted + np.array([[0.0, 0.0, 0.02], [0.0, 0.0, 0.45], [0.0, 0.0, 0.45]])
    accepted = np.array([True, True, False])
    sd_theta = 1.0 / np.sqrt(info_motion[0, 2, 2])
    assert 0.05 < sd_theta < 0.1
    surprise = fit_surprise(fitted, predicted, accepted, info_fit, info_motion)
    assert surprise[0] < 0.1  # well within one sd
    assert surprise[1] > 10.0  # 0.45 rad: more than 6 sd out
    assert surprise[2] == 0.0  # a rejected fit keeps its motion sample: no fit to weigh


def test_what_the_scan_leaves_open_costs_nothing() -> None:
    """A corridor fixes the heading and the offset across it, not the position along it: a fit 0.5 m
    along the corridor from the prediction is not penalised, the same offset across it is."""
    particles, info_motion, predicted = _one_metre_ahead(2)
    info_fit = np.tile(np.diag([0.0, 4e4, 4e4]), (2, 1, 1))  # no information along x
    fitted = predicted + np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    surprise = fit_surprise(fitted, predicted, np.array([True, True]), info_fit, info_motion)
    assert surprise[0] < 1e-6
    assert surprise[1] > 5.0
