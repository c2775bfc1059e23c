"""Keep precise odometry's local precision in the final trajectory.

The front end places every key frame by a scan match: globally consistent, but each pose carries the
match's own white noise (centimetres outdoors at long range). A fibre-optic gyro with good wheel
encoders is far more precise than that from one key frame to the next, and the match noise would
replace its precision. How precise each source is, is measured on the log itself: between key
frames ``L`` steps apart, the front end's relative motion differs from the odometry's by the noise of
two matches (fixed) plus ``L`` steps of odometry noise (growing): in heading, and in the distance
between the two key frames (which a heading error barely changes), so

    E |difference over L steps|^2 = 2 sd_match^2 + L sd_odometry^2,

fitted over L = 1..16 separately for heading and translation. The final poses then solve a small
pose graph: each key frame held at its optimised pose with sd_match, consecutive key frames tied by
the odometry increment with sd_odometry. Where odometry is the worse source (wheels alone, rough
odometry) the fit says so and the poses stay as they were; where it is the better one, the
trajectory follows it locally and the matches globally.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_engine.poses import relative, wrap_angle

LAGS = (1, 2, 4, 8, 16)
# median of |N(0, 1)|: median -> sd
HALF_NORMAL_MEDIAN = 0.6745
# odometry edges only matter where they are this much more precise per step than a match [ratio]
MIN_ADVANTAGE = 1.0
MIN_KEY_FRAMES = 3 * LAGS[-1]
# floors [m, rad]: no source is trusted beyond these
MATCH_SD_FLOOR = (1e-3, 1e-4)
ODOMETRY_SD_FLOOR = (2e-4, 2e-5)


@dataclass(frozen=True)
class NoiseEstimate:
    """Standard deviations measured on the log: a match's pose noise and the odometry's noise per
    key-frame step, for translation (per axis) [m] and heading [rad]."""

    match_sd_m: float
    match_sd_rad: float
    odometry_sd_m: float
    odometry_sd_rad: float

    @property
    def odometry_helps(self) -> bool:
        """Odometry is locally more precise than the matches in translation or heading."""
        return (self.odometry_sd_m * MIN_ADVANTAGE < self.match_sd_m
                or self.odometry_sd_rad * MIN_ADVANTAGE < self.match_sd_rad)

    def summary(self) -> dict[str, float]:
        return {"match_sd_m": round(self.match_sd_m, 5), "match_sd_rad": round(self.match_sd_rad, 6),
                "odometry_sd_m_per_step": round(self.odometry_sd_m, 5),
                "odometry_sd_rad_per_step": round(self.odometry_sd_rad, 6)}


def _fit_growth(lags: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """Fixed part a and growth per step b (both >= 0) of variance = a + b L: non-negative least
    squares on relative errors. Systematic drift (the front end's map bending, the odometry's bias)
    also grows and is counted as odometry noise: the odometry is trusted less, never more."""
    from scipy.optimize import nnls  # imported on first use, like GTSAM: after the front end's peak

    A = np.stack([np.ones_like(lags), lags], axis=1) / variances[:, None]
    (a, b), _ = nnls(A, np.ones_like(lags))
    return float(a), float(b)


def estimate_noise(path: np.ndarray, odometry: np.ndarray) -> NoiseEstimate | None:
    """Match and odometry noise from the front end's key-frame ``path`` (K, 3) and the odometry poses
    at the same key frames ``odometry`` (K, 3); None for a drive too short to tell. Medians, so that
    a few bad matches or wheel slips do not decide it."""
    path = np.asarray(path, np.float64)
    odometry = np.asarray(odometry, np.float64)
    if len(path) < MIN_KEY_FRAMES:
        return None
    lags = np.array(LAGS, np.float64)
    var_xy = np.empty(len(LAGS))
    var_th = np.empty(len(LAGS))
    for n, lag in enumerate(LAGS):
        front = relative(path[:-lag], path[lag:])
        odo = relative(odometry[:-lag], odometry[lag:])
        # translation: the difference of the distances travelled, which a heading error leaves alone
        # (the heading is measured on its own), one axis' worth of noise
        d_xy = np.abs(np.hypot(front[:, 0], front[:, 1]) - np.hypot(odo[:, 0], odo[:, 1]))
        d_th = np.abs(wrap_angle(front[:, 2] - odo[:, 2]))
        var_xy[n] = (np.median(d_xy) / HALF_NORMAL_MEDIAN) ** 2
        var_th[n] = (np.median(d_th) / HALF_NORMAL_MEDIAN) ** 2
    a_xy, b_xy = _fit_growth(lags, np.maximum(var_xy, 1e-12))
    a_th, b_th = _fit_growth(lags, np.maximum(var_th, 1e-16))
    return NoiseEstimate(match_sd_m=max(float(np.sqrt(a_xy / 2.0)), MATCH_SD_FLOOR[0]),
                         match_sd_rad=max(float(np.sqrt(a_th / 2.0)), MATCH_SD_FLOOR[1]),
                         odometry_sd_m=max(float(np.sqrt(b_xy)), ODOMETRY_SD_FLOOR[0]),
                         odometry_sd_rad=max(float(np.sqrt(b_th)), ODOMETRY_SD_FLOOR[1]))


def smooth_with_odometry(poses: np.ndarray, odometry: np.ndarray, noise: NoiseEstimate) -> np.ndarray:
    """Key-frame ``poses`` (K, 3, world) held with the match noise and tied in sequence by the
    odometry's increments (``odometry`` (K, 3)) with the odometry noise: the least-squares poses."""
    import gtsam

    poses = np.asarray(poses, np.float64)
    steps = relative(odometry[:-1], odometry[1:])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    hold = gtsam.noiseModel.Diagonal.Sigmas(np.array([noise.match_sd_m, noise.match_sd_m, noise.match_sd_rad]))
    tie = gtsam.noiseModel.Diagonal.Sigmas(np.array([noise.odometry_sd_m, noise.odometry_sd_m,
                                                     noise.odometry_sd_rad]))
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
        graph.add(gtsam.PriorFactorPose2(k, gtsam.Pose2(*p), hold))
    for k, s in enumerate(steps):
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, gtsam.Pose2(*s), tie))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    out = np.empty_like(poses)
    for k in range(len(poses)):
        p = result.atPose2(k)
        out[k] = (p.x(), p.y(), p.theta())
    return out
