"""Particle weights: log-space normalisation, effective sample size, low-variance resampling, and how
many particles a posterior's spread needs (KLD-sampling)."""

from __future__ import annotations

import math

import numpy as np

# the standard normal's 0.99 quantile: KLD-sampling's bound holds with probability 0.99
KLD_Z = 2.3263


def normalize_log_weights(log_weights: np.ndarray) -> np.ndarray:
    """Normalised weights (sum 1) from log-weights, stable for any common offset (log-sum-exp).
    Non-finite log-weights (-inf) get weight 0; all -inf gives uniform weights."""
    log_weights = np.asarray(log_weights, dtype=np.float64)
    finite = np.isfinite(log_weights)
    if not finite.any():
        return np.full(log_weights.shape, 1.0 / log_weights.size)
    shifted = np.where(finite, log_weights - log_weights[finite].max(), -np.inf)
    w = np.exp(shifted)
    return w / w.sum()


def log_sum_exp(log_weights: np.ndarray) -> float:
    """log(sum(exp(log_weights))) without overflow or underflow."""
    log_weights = np.asarray(log_weights, dtype=np.float64)
    top = np.max(log_weights)
    if not np.isfinite(top):
        return float(top)
    return float(top + np.log(np.sum(np.exp(log_weights - top))))


def n_eff(weights: np.ndarray) -> float:
    """Effective sample size 1 / sum(w^2) of normalised weights."""
    weights = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(weights * weights))


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator, count: int | None = None) -> np.ndarray:
    """Systematic (low-variance) resampling: (count,) ancestor indices (default count: as many as
    there are weights), particle i is drawn ``floor(count w_i)`` or ``ceil(count w_i)`` times.
    ``weights`` must be normalised."""
    weights = np.asarray(weights, dtype=np.float64)
    n = weights.size if count is None else int(count)
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right").astype(np.int64)


def should_resample(weights: np.ndarray, threshold: float) -> bool:
    """True when N_eff < threshold * N."""
    return n_eff(weights) < threshold * np.asarray(weights).size


def kld_sample_count(occupied_bins: int, error: float, z: float = KLD_Z) -> int:
    """Particles that KLD-sampling (Fox 2003) asks for when the samples occupy ``occupied_bins`` bins:
    enough that the divergence between the sample set and the posterior stays below ``error`` with
    the probability whose standard-normal quantile is ``z`` (Wilson-Hilferty approximation of the
    chi-square quantile). One bin asks for 1."""
    k = int(occupied_bins)
    if k <= 1:
        return 1
    a = 2.0 / (9.0 * (k - 1))
    return int(math.ceil((k - 1) / (2.0 * error) * (1.0 - a + math.sqrt(a) * z) ** 3))


def occupied_bins(poses: np.ndarray, bin_xy_m: float, bin_theta_rad: float) -> int:
    """Number of distinct (x, y, heading) bins [m, m, rad] that the (N, 3) poses fall in."""
    poses = np.asarray(poses, dtype=np.float64)
    keys = np.floor(np.column_stack([poses[:, 0] / bin_xy_m, poses[:, 1] / bin_xy_m,
                                     poses[:, 2] / bin_theta_rad])).astype(np.int64)
    return int(len(np.unique(keys, axis=0)))
