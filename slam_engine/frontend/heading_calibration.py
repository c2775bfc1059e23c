"""Online calibration of the odometry's systematic heading error.

Raw wheel odometry turns wrongly in two systematic ways (Borenstein's UMBmark): a wrong effective
track width scales every turn, and unequal wheel diameters bend every metre driven. The model here:

    true turn = scale * odometry turn + drift_rad_per_m * signed distance

between two processed scans. The scan matcher measures the true turn of every particle whose match
was accepted; a ridge least-squares fit of all those measurements (priors: scale 1, drift 0) gives
the current estimate. It is corrected only once it lies outside a dead band around (1, 0): small
systematic errors are absorbed by the scan-matched proposal, and correcting them cost accuracy on
well-calibrated odometry (intel: estimated scale 0.95), while large ones (turns 1.6x too large and
0.03 rad/m drift) make the matches fail without the correction.
"""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.motion_models import apply_odometry_increments, odometry_increments
from slam_engine.model.poses import wrap_angle

# a step counts only when most particles' matches were accepted
MIN_ACCEPTED_SHARE = 0.5
# the estimate stays inside these limits (beyond them odometry is unusable, not biased)
SCALE_LIMITS = (0.5, 2.0)
DRIFT_LIMIT_RAD_PER_M = 0.5
# steps shorter than this say little about the distance scale [m]
MIN_DISTANCE_STEP_M = 0.05


class HeadingCalibration:
    """Running ridge fit of ``true turn = scale * odometry turn + drift * distance``.

    ``prior_scale_rad2``: weight of the prior ``scale = 1`` [rad^2 of odometry turn it is worth];
    ``prior_drift_m2``: weight of the prior ``drift = 0`` [m^2 of travel it is worth];
    ``scale_band`` / ``drift_band_rad_per_m``: dead bands of the correction;
    ``enabled``: False corrects nothing (scale 1, drift 0)."""

    def __init__(self, prior_scale_rad2: float, prior_drift_m2: float, scale_band: float = 0.1,
                 drift_band_rad_per_m: float = 0.01, enabled: bool = True, prior_distance_m2: float = 100.0,
                 distance_band: float = 0.02):
        self.enabled = bool(enabled)
        self.scale_band = float(scale_band)
        self.drift_band_rad_per_m = float(drift_band_rad_per_m)
        self._prior = np.diag([float(prior_scale_rad2), float(prior_drift_m2)])
        self._normal = self._prior.copy()  # X^T X + prior
        self._rhs = np.array([float(prior_scale_rad2), 0.0])  # X^T y + prior * (1, 0)
        self.scale = 1.0
        self.drift_rad_per_m = 0.0
        self.steps_used = 0
        # distance scale: least squares of matched = scale * odometry distance, prior scale 1
        self.distance_band = float(distance_band)
        self._distance_normal = float(prior_distance_m2)
        self._distance_rhs = float(prior_distance_m2)
        self.distance_scale = 1.0
        self.distance_steps_used = 0

    @property
    def applied_scale(self) -> float:
        """The turn scale the correction uses: the estimate once it is ``scale_band`` or more from 1."""
        return self.scale if abs(self.scale - 1.0) >= self.scale_band else 1.0

    @property
    def applied_drift_rad_per_m(self) -> float:
        """The drift [rad/m] the correction uses: the estimate once it is outside its band."""
        return self.drift_rad_per_m if abs(self.drift_rad_per_m) >= self.drift_band_rad_per_m else 0.0

    @property
    def applied_distance_scale(self) -> float:
        """The distance scale the correction uses: the estimate once it is ``distance_band`` or more from 1."""
        return self.distance_scale if abs(self.distance_scale - 1.0) >= self.distance_band else 1.0

    def corrected_target(self, odom_from: np.ndarray, odom_to: np.ndarray) -> np.ndarray:
        """The odometry pose ``odom_to`` as the corrected motion from ``odom_from`` would reach it:
        both rotations of the rot1-trans-rot2 increment scaled, the drift split between them."""
        scale, drift, stretch = self.applied_scale, self.applied_drift_rad_per_m, self.applied_distance_scale
        if not self.enabled or (scale == 1.0 and drift == 0.0 and stretch == 1.0):
            return np.asarray(odom_to, dtype=np.float64)
        rot1, trans, rot2 = odometry_increments(odom_from, odom_to)
        bend = 0.5 * drift * trans
        return apply_odometry_increments(np.asarray(odom_from, dtype=np.float64), scale * rot1 + bend,
                                         stretch * trans, scale * rot2 + bend)

    def observe_distance(self, odom_from: np.ndarray, odom_to: np.ndarray, before: np.ndarray, after: np.ndarray,
                         accepted: np.ndarray, jtj: np.ndarray) -> None:
        """One processed step's travelled distance as the matches measured it: the mean displacement
        of the accepted particles along the odometry's direction of travel, used only when the scan
        constrains that direction (its information along it, from the fits' Gauss-Newton matrices
        ``jtj`` (N, 3, 3), is at least a third of the information across it: not in a corridor)."""
        if not self.enabled or accepted.mean() < MIN_ACCEPTED_SHARE:
            return
        rot1, trans, _ = odometry_increments(odom_from, odom_to)
        if abs(trans) < MIN_DISTANCE_STEP_M:
            return
        heading = before[accepted, 2] + rot1
        u = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        info = jtj[accepted][:, :2, :2]
        along = np.einsum("ni,nij,nj->n", u, info, u)
        across = np.trace(info, axis1=1, axis2=2) - along
        if np.median(along) < 0.33 * np.median(across):
            return
        moved = after[accepted, :2] - before[accepted, :2]
        matched = float(np.mean(np.einsum("ni,ni->n", moved, u))) * np.sign(trans)
        self._distance_normal += float(trans) ** 2
        self._distance_rhs += abs(float(trans)) * matched
        self.distance_steps_used += 1
        self.distance_scale = float(np.clip(self._distance_rhs / self._distance_normal, *SCALE_LIMITS))

    def observe(self, odom_from: np.ndarray, odom_to: np.ndarray, before: np.ndarray, after: np.ndarray,
                accepted: np.ndarray) -> None:
        """One processed step: odometry poses ``odom_from -> odom_to``, particle poses (N, 3)
        ``before`` the step and ``after`` their scan match, ``accepted`` (N,) whether each match was
        accepted. The mean turn of the accepted particles is the step's measured true turn."""
        if not self.enabled or accepted.mean() < MIN_ACCEPTED_SHARE:
            return
        rot1, trans, rot2 = odometry_increments(odom_from, odom_to)
        odom_turn = float(rot1 + rot2)
        turns = wrap_angle(after[accepted, 2] - before[accepted, 2])
        x = np.array([odom_turn, float(trans)])
        self._normal += np.outer(x, x)
        self._rhs += x * float(np.mean(turns))
        self.steps_used += 1
        scale, drift = np.linalg.solve(self._normal, self._rhs)
        self.scale = float(np.clip(scale, *SCALE_LIMITS))
        self.drift_rad_per_m = float(np.clip(drift, -DRIFT_LIMIT_RAD_PER_M, DRIFT_LIMIT_RAD_PER_M))

    def summary(self) -> dict:
        """Estimated and applied heading scale and drift [rad/m], and the steps measured."""
        return {"enabled": self.enabled, "heading_scale": round(self.scale, 4),
                "heading_drift_rad_per_m": round(self.drift_rad_per_m, 5),
                "applied_heading_scale": round(self.applied_scale, 4),
                "applied_heading_drift_rad_per_m": round(self.applied_drift_rad_per_m, 5),
                "calibration_steps": self.steps_used, "distance_scale": round(self.distance_scale, 4),
                "applied_distance_scale": round(self.applied_distance_scale, 4),
                "distance_calibration_steps": self.distance_steps_used}

