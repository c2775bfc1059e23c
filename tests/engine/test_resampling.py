"""Weights in log space, effective sample size and low-variance resampling."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.resampling import (
    kld_sample_count,
    log_sum_exp,
    low_variance_resample,
    n_eff,
    normalize_log_weights,
    occupied_bins,
    should_resample,
)


def test_normalisation_is_stable_far_below_zero() -> None:
    w = normalize_log_weights(np.array([-1e6, -1e6 + np.log(3.0), -np.inf]))
    np.testing.assert_allclose(w, [0.25, 0.75, 0.0])
    assert abs(log_sum_exp(np.array([-1e6, -1e6])) - (-1e6 + np.log(2.0))) < 1e-6
    np.testing.assert_allclose(normalize_log_weights(np.full(4, -np.inf)), 0.25)


def test_n_eff_bounds() -> None:
    assert abs(n_eff(np.full(10, 0.1)) - 10.0) < 1e-9
    assert n_eff(np.eye(1, 10)[0]) == 1.0
    assert should_resample(np.array([0.97, 0.01, 0.01, 0.01]), 0.5)
    assert not should_resample(np.full(4, 0.25), 0.5)


def test_systematic_resampling_draws_floor_or_ceil_of_n_times_weight() -> None:
    weights = np.array([0.5, 0.25, 0.125, 0.0625, 0.0625])
    rng = np.random.default_rng(3)
    n = weights.size
    totals = np.zeros(n)
    for _ in range(2000):
        counts = np.bincount(low_variance_resample(weights, rng), minlength=n)
        assert counts.sum() == n
        assert np.all(counts >= np.floor(n * weights)) and np.all(counts <= np.ceil(n * weights))
        totals += counts
    # unbiased: on average particle i is drawn n * w_i times
    np.testing.assert_allclose(totals / 2000, n * weights, atol=0.05)


def test_resampling_draws_the_count_asked_for() -> None:
    weights = np.array([0.5, 0.25, 0.125, 0.125])
    rng = np.random.default_rng(1)
    for count in (2, 8, 12):
        counts = np.bincount(low_variance_resample(weights, rng, count), minlength=weights.size)
        assert counts.sum() == count
        assert np.all(counts >= np.floor(count * weights)) and np.all(counts <= np.ceil(count * weights))
    # the default count is the number of weights, with the same draws as asking for it
    a = low_variance_resample(weights, np.random.default_rng(5))
    b = low_variance_resample(weights, np.random.default_rng(5), weights.size)
    np.testing.assert_array_equal(a, b)


def test_kld_count_grows_with_the_bins_the_samples_occupy() -> None:
    assert kld_sample_count(1, 0.5) == 1
    assert kld_sample_count(0, 0.5) == 1
    # Fox 2003 with the Wilson-Hilferty chi-square quantile, z = 2.3263 (99 %): k = 2 bins
    a = 2.0 / 9.0
    assert kld_sample_count(2, 0.5) == int(np.ceil(1.0 / (2 * 0.5) * (1 - a + np.sqrt(a) * 2.3263) ** 3)) == 7
    counts = [kld_sample_count(k, 0.5) for k in range(1, 40)]
    assert counts == sorted(counts) and counts[-1] > 50
    # a tighter bound asks for more
    assert kld_sample_count(10, 0.05) > 9 * kld_sample_count(10, 0.5)


def test_occupied_bins_counts_distinct_pose_cells() -> None:
    poses = np.array([[0.01, 0.01, 0.001], [0.02, 0.04, 0.005],  # one bin of 0.05 m, 0.0175 rad
                      [0.06, 0.01, 0.001],  # next x bin
                      [0.01, 0.01, 0.02],  # next heading bin
                      [-0.01, 0.01, 0.001]])  # x below zero
    assert occupied_bins(poses, 0.05, 0.0175) == 4
    assert occupied_bins(poses, 1.0, 1.0) == 2  # x -0.01 floors to bin -1
