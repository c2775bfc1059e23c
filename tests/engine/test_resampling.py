"""Weights in log space, effective sample size and low-variance resampling."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.resampling import (
    log_sum_exp,
    low_variance_resample,
    n_eff,
    normalize_log_weights,
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
