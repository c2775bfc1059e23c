"""Particle weights: log-space normalisation, effective sample size, low-variance resampling."""

from __future__ import annotations

import numpy as np


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


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic (low-variance) resampling: (N,) ancestor indices, particle i is drawn
    ``floor(N w_i)`` or ``ceil(N w_i)`` times. ``weights`` must be normalised."""
    weights = np.asarray(weights, dtype=np.float64)
    n = weights.size
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right").astype(np.int64)


def should_resample(weights: np.ndarray, threshold: float) -> bool:
    """True when N_eff < threshold * N."""
    return n_eff(weights) < threshold * np.asarray(weights).size
