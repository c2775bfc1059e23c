"""How precise a log's odometry is, compared with its scan matches, measured on the log itself.

Between key frames ``L`` steps apart, the front end's relative motion differs from the odometry's by
the noise of two matches (fixed) plus ``L`` steps of odometry noise (growing): in heading, and in the
distance between the two key frames (which a heading error barely changes), so

    E |difference over L steps|^2 = 2 sd_match^2 + L sd_odometry^2,

fitted over L = 1..16 separately for heading and translation. The front end uses it to size its
motion model (:class:`OdometryPrecision`), the back end to keep precise odometry's local precision
(:mod:`slam_engine.backend.odometry_smoothing`).

That difference cannot tell which source drifts: a front end whose matches each carry the last
step's error (scan-to-map matching along a street, where the scans constrain the travel direction
weakly) grows like noisy odometry and is counted as such. Where a log has wheel encoders *and* a
gyro, the wheels are checked against the gyro instead (:func:`wheel_distance_sd_m`): their heading
change ``(right - left) / track`` disagrees with the gyro's by the difference of the two sides'
errors, whose spread bounds the travelled distance's (the mean of the sides) independently of the
scans. The odometry's translation noise is then the smaller of the two figures.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slam_engine.model.poses import relative, wrap_angle

LAGS = (1, 2, 4, 8, 16)
# median of |N(0, 1)|: median -> sd
HALF_NORMAL_MEDIAN = 0.6745
# odometry edges only matter where they are this much more precise per step than a match [ratio]
MIN_ADVANTAGE = 1.0
MIN_KEY_FRAMES = 3 * LAGS[-1]
# floors [m, rad]: no source is trusted beyond these
MATCH_SD_FLOOR = (1e-3, 1e-4)
ODOMETRY_SD_FLOOR = (2e-4, 2e-5)
# the front end trusts the odometry only where it is this fraction of the model's noise or less ...
MAX_TRUSTED_SCALE = 0.25
# ... and this many times more precise per step than a match (in translation or heading) [ratio];
# once trusted, MIN_ADVANTAGE keeps it so
MIN_TRUSTED_ADVANTAGE = 2.0
# a step counts for the wheel check when the wheels moved at least this much [m]
MIN_WHEEL_STEP_M = 1e-3
# median absolute deviation -> sd of a normal distribution
MAD_TO_SD = 1.4826


@dataclass(frozen=True)
class NoiseEstimate:
    """Standard deviations measured on the log: a match's pose noise and the odometry's noise per
    key-frame step, for translation (per axis) [m] and heading [rad]."""

    match_sd_m: float
    match_sd_rad: float
    odometry_sd_m: float
    odometry_sd_rad: float
    wheel_sd_m: float | None = None  # the wheels' distance noise per step, checked against the gyro [m]

    @property
    def odometry_helps(self) -> bool:
        """Odometry is locally more precise than the matches in translation or heading."""
        return self.more_precise_by(MIN_ADVANTAGE)

    def more_precise_by(self, ratio: float) -> bool:
        """Odometry is ``ratio`` times more precise per step than the matches in translation or heading."""
        return self.odometry_sd_m * ratio < self.match_sd_m or self.odometry_sd_rad * ratio < self.match_sd_rad

    def summary(self) -> dict[str, float]:
        return {"match_sd_m": round(self.match_sd_m, 5), "match_sd_rad": round(self.match_sd_rad, 6),
                "odometry_sd_m_per_step": round(self.odometry_sd_m, 5),
                "odometry_sd_rad_per_step": round(self.odometry_sd_rad, 6),
                **({} if self.wheel_sd_m is None else {"wheel_sd_m_per_step": round(self.wheel_sd_m, 5)})}


def _fit_growth(lags: np.ndarray, variances: np.ndarray) -> tuple[float, float]:
    """Fixed part a and growth per step b (both >= 0) of variance = a + b L: non-negative least
    squares on relative errors. Systematic drift (the front end's map bending, the odometry's bias)
    also grows and is counted as odometry noise: the odometry is trusted less, never more.

    Two unknowns: the optimum is the unconstrained fit or lies on an axis, so the candidates are
    compared directly (scipy.optimize.nnls gives the same, but importing it costs the front end
    37 MB, an eighth of a whole intel run)."""
    A = np.stack([np.ones_like(lags), lags], axis=1) / variances[:, None]
    y = np.ones_like(lags)
    candidates = [np.zeros(2)]
    for column in range(2):  # one unknown, the other 0
        x = np.zeros(2)
        x[column] = max(0.0, float(A[:, column] @ y) / float(A[:, column] @ A[:, column]))
        candidates.append(x)
    both = np.linalg.lstsq(A, y, rcond=None)[0]
    if (both >= 0).all():
        candidates.append(both)
    a, b = min(candidates, key=lambda x: float(np.sum((A @ x - y) ** 2)))
    return float(a), float(b)


def wheel_distance_sd_m(wheels: np.ndarray) -> float | None:
    """The wheels' travelled-distance noise per step [m], from ``wheels`` (K, 3): cumulative left and
    right side distances [m] and the gyro's yaw [rad] at each key frame (:meth:`OdometryIntegrator.
    wheel_check`); None for too few moving steps.

    Per step, the sides' difference ``dr - dl`` is fitted as ``track * dyaw`` (the effective track,
    least squares: a skid steer's is wider than its wheels'); what is left is ``e_r - e_l``, the
    difference of the two sides' errors (the gyro's own error adds to it: a bound, never less). With
    independent sides of equal noise, the distance ``(dl + dr) / 2`` carries half that spread. A
    slip that both sides share (a common scale error) is not seen here: the heading calibration's
    distance scale and the matches correct it."""
    wheels = np.asarray(wheels, np.float64)
    steps = np.diff(wheels, axis=0)
    moving = np.abs(0.5 * (steps[:, 0] + steps[:, 1])) >= MIN_WHEEL_STEP_M
    if np.count_nonzero(moving) < MIN_KEY_FRAMES:
        return None
    sides, yaw = steps[moving, 1] - steps[moving, 0], steps[moving, 2]
    track = float(np.dot(sides, yaw) / np.dot(yaw, yaw)) if np.dot(yaw, yaw) > 0 else 0.0
    residual = sides - track * yaw
    spread = MAD_TO_SD * float(np.median(np.abs(residual - np.median(residual))))
    return 0.5 * spread


def estimate_noise(path: np.ndarray, odometry: np.ndarray,
                   wheels: Sequence[np.ndarray | None] | np.ndarray | None = None) -> NoiseEstimate | None:
    """Match and odometry noise from the front end's key-frame ``path`` (K, 3) and the odometry poses
    at the same key frames ``odometry`` (K, 3); None for a drive too short to tell. Medians, so that
    a few bad matches or wheel slips do not decide it. ``wheels``: each key frame's wheel and gyro
    readings (:meth:`OdometryIntegrator.wheel_check`, None without both); where every key frame has
    them, their cross-check (:func:`wheel_distance_sd_m`) caps the translation noise."""
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
    odometry_sd_m = float(np.sqrt(b_xy))
    checked = wheels is not None and len(wheels) > 0 and all(w is not None for w in wheels)
    wheel_sd_m = wheel_distance_sd_m(np.array(wheels)) if checked else None
    if wheel_sd_m is not None:
        odometry_sd_m = min(odometry_sd_m, wheel_sd_m)
    return NoiseEstimate(match_sd_m=max(float(np.sqrt(a_xy / 2.0)), MATCH_SD_FLOOR[0]),
                         match_sd_rad=max(float(np.sqrt(a_th / 2.0)), MATCH_SD_FLOOR[1]),
                         odometry_sd_m=max(odometry_sd_m, ODOMETRY_SD_FLOOR[0]),
                         odometry_sd_rad=max(float(np.sqrt(b_th)), ODOMETRY_SD_FLOOR[1]),
                         wheel_sd_m=wheel_sd_m)


class OdometryPrecision:
    """The front end's running view of :func:`estimate_noise`: every ``every_steps`` processed steps,
    the last ``window_steps`` key frames (the fitted poses of the best particle, before any fusion
    with the odometry, so that trusting the odometry cannot feed on itself) against the odometry.

    Where the odometry is measured to be more precise than the matches, the motion model's standard
    deviations are scaled down to what was measured (``rot_scale`` for the heading terms,
    ``trans_scale`` for the distance terms, at most 1: the configured model is an upper bound) and the
    proposal fuses each match with its motion sample; elsewhere the model stays as configured."""

    def __init__(self, every_steps: int = 25, window_steps: int = 200, min_scale: float = 0.02):
        self.every_steps = int(every_steps)
        self.window_steps = int(window_steps)
        self.min_scale = float(min_scale)
        self._fitted: deque[np.ndarray] = deque(maxlen=self.window_steps)
        self._odometry: deque[np.ndarray] = deque(maxlen=self.window_steps)
        self._model_sd: deque[tuple[float, float]] = deque(maxlen=self.window_steps)
        self._wheels: deque[np.ndarray | None] = deque(maxlen=self.window_steps)
        self.estimate: NoiseEstimate | None = None
        self.trusted = False
        self.rot_scale = 1.0
        self.trans_scale = 1.0
        self.changes = 0
        self._steps = 0

    def observe(self, fitted_pose: np.ndarray, odometry_pose: np.ndarray, model_sd_m: float,
                model_sd_rad: float, wheels: np.ndarray | None = None) -> None:
        """One processed step: the best particle's fitted pose, the odometry pose, the configured
        model's standard deviations of that step's motion [m, rad] and, where the log has encoders and
        a gyro, their cumulative readings (:meth:`OdometryIntegrator.wheel_check`)."""
        self._wheels.append(None if wheels is None else np.asarray(wheels, np.float64).copy())
        self._fitted.append(np.asarray(fitted_pose, np.float64).copy())
        self._odometry.append(np.asarray(odometry_pose, np.float64).copy())
        self._model_sd.append((float(model_sd_m), float(model_sd_rad)))
        self._steps += 1
        if self._steps % self.every_steps == 0:
            self._update()

    def _update(self) -> None:
        estimate = estimate_noise(np.array(self._fitted), np.array(self._odometry), list(self._wheels))
        if estimate is None:
            return
        self.estimate = estimate
        model = np.median(np.array(self._model_sd), axis=0)
        trans_scale = float(np.clip(estimate.odometry_sd_m / max(model[0], 1e-9), self.min_scale, 1.0))
        rot_scale = float(np.clip(estimate.odometry_sd_rad / max(model[1], 1e-12), self.min_scale, 1.0))
        # trusted only when clearly so: more precise than the matches and several times more precise
        # than the model says (a rover's first scans looked 2x better than the model: not enough).
        # Once trusted, kept while the odometry stays the more precise source at all: a front end that
        # drifts has no white part, and its match noise falls to the floor in some windows
        advantage = MIN_ADVANTAGE if self.trusted else MIN_TRUSTED_ADVANTAGE
        trusted = estimate.more_precise_by(advantage) and min(trans_scale, rot_scale) <= MAX_TRUSTED_SCALE
        self.trans_scale, self.rot_scale = (trans_scale, rot_scale) if trusted else (1.0, 1.0)
        self.changes += int(trusted != self.trusted)
        self.trusted = trusted

    def scaled(self, alphas: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        """The motion model's ``(rot_from_rot, rot_from_trans, trans_from_trans, trans_from_rot)``
        scaled to the measured precision."""
        a1, a2, a3, a4 = alphas
        return (a1 * self.rot_scale, a2 * self.rot_scale, a3 * self.trans_scale, a4 * self.trans_scale)

    def summary(self) -> dict[str, object]:
        """For run.json."""
        return {"trusted": self.trusted, "rot_scale": round(self.rot_scale, 4),
                "trans_scale": round(self.trans_scale, 4), "changes": self.changes,
                **(self.estimate.summary() if self.estimate is not None else {})}
