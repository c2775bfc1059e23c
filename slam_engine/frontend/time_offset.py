"""The time offset between a LiDAR's stamps and the odometry's clock, estimated online, and scan
de-skew.

**Offset.** A scan stamped ``t`` was measured (its middle beam) at ``t + offset`` on the odometry's
clock; a scan that lags its wheel ticks by 0.15 s (BreezySLAM's exp2) has offset -0.15 s. Pairing
such a scan with the odometry at its stamp puts the heading wrong by about ``turn rate x offset``
and, between two scans, the turn wrong by ``offset x (change of turn rate)``: the scan matcher must
absorb that at every start and end of a turn, and the maps blur where it cannot.

**Estimate** (:class:`TimeOffsetEstimator`). Each processed step measures, by its accepted scan
matches, the vehicle's true turn ``m_k`` since the previous processed scan. For a candidate offset
``d`` the odometry predicts the turn ``p_k(d) = scale * (theta(t_k + d) - theta(t_(k-1) + d)) +
drift * distance`` (the heading calibration's scale and drift). Over a grid of candidates (5 ms
apart within +-``max_abs_s``) the estimator sums a truncated squared residual
``min((m_k - p_k(d))^2, cap^2)`` over the steps, plus a prior ``prior_weight * d^2``, and takes the
minimum (refined by a parabola). Only steps where the turn rate changes tell offsets apart. The
estimate is applied once (a) the cost at it lies far below the cost at offset 0 (``min_evidence``
mean squared residuals: the cost can have several shallow minima on a log without an offset), (b)
the cost's curvature there gives a standard error below ``max_se_s``, and (c) it lies outside a dead
band and three standard errors from 0 (small offsets are left to the matcher, and a log without one
keeps exactly the pairing it had). Steps are evaluated once the odometry has passed
``t_k + max_abs_s`` (so that every candidate is interpolated, not extrapolated); the estimate never
feeds back into what it measures: the matched turns are the vehicle's whatever offset is applied.

**De-skew** (:func:`sweep_poses`). A scanner sweeps its beams one after another (``time_increment_s``
of the :class:`~slam_engine.model.drive_log.LidarModel`, where the log or the sensor's specification gives
it); a vehicle turning at 2 rad/s turns 0.13 rad during a URG-04LX's 67 ms sweep, which bends a wall
3 m away by +-10 cm. Each beam's end point is moved into the vehicle frame at the middle beam's time
by the odometry's motion between the two instants (interpolated in :class:`OdometryHistory`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from slam_engine.model.poses import relative, wrap_angle

# candidate offsets are this far apart [s]
GRID_STEP_S = 0.005
# the cost's curvature is measured over this many grid steps either side of its minimum
CURVATURE_STEPS = 4
# an estimate is applied only this many standard errors away from 0
SIGNIFICANT_SE = 3.0
# a sweep whose end points move less than this [m, rad] is left as it is
STILL_M = 1e-4
STILL_RAD = 1e-5


class OdometryHistory:
    """The odometry poses of the last ``keep_s`` seconds (heading unwrapped), interpolated at any
    time inside them; times outside take the end pose."""

    def __init__(self, keep_s: float):
        self.keep_s = float(keep_s)
        self._rows: deque[tuple[float, float, float, float]] = deque()
        self._cache: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def t_latest(self) -> float | None:
        return self._rows[-1][0] if self._rows else None

    def append(self, t_s: float, pose: np.ndarray) -> None:
        """Add the odometry pose at ``t_s`` (time order; an equal stamp replaces the last)."""
        theta = float(pose[2])
        if self._rows:
            last_t, _, _, last_theta = self._rows[-1]
            theta = last_theta + float(wrap_angle(theta - last_theta))
            if t_s <= last_t:
                self._rows.pop()
        self._rows.append((float(t_s), float(pose[0]), float(pose[1]), theta))
        while len(self._rows) > 2 and self._rows[1][0] < t_s - self.keep_s:
            self._rows.popleft()
        self._cache = None

    def covers(self, t_s: float) -> bool:
        """Whether ``t_s`` lies within the kept poses (interpolated, not held at an end)."""
        return bool(self._rows) and self._rows[0][0] <= t_s <= self._rows[-1][0]

    def _array(self) -> np.ndarray:
        if self._cache is None:
            self._cache = np.array(self._rows, dtype=np.float64).reshape(-1, 4)
        return self._cache

    def poses_at(self, t_s: np.ndarray) -> np.ndarray:
        """(M, 3) poses at ``t_s`` (M,), heading unwrapped."""
        rows = self._array()
        if len(rows) == 0:
            raise ValueError("no odometry yet")
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        return np.column_stack([np.interp(t_s, rows[:, 0], rows[:, k]) for k in (1, 2, 3)])

    def pose_at(self, t_s: float) -> np.ndarray:
        """(3,) pose at ``t_s`` (heading wrapped)."""
        pose = self.poses_at(np.array([t_s]))[0]
        pose[2] = wrap_angle(pose[2])
        return pose

    def headings_at(self, t_s: np.ndarray) -> np.ndarray:
        """Unwrapped headings [rad] at ``t_s``."""
        rows = self._array()
        return np.interp(np.asarray(t_s, dtype=np.float64), rows[:, 0], rows[:, 3])


def sweep_poses(history: OdometryHistory, t_ref_s: float, beam_offsets_s: np.ndarray,
                heading_scale: float = 1.0) -> np.ndarray | None:
    """(B, 3) the vehicle's pose when each beam was measured (``t_ref_s + beam_offsets_s``) in its
    frame at ``t_ref_s``, the odometry's turn scaled by ``heading_scale``; None when the vehicle
    did not move during the sweep (nothing to correct)."""
    poses = history.poses_at(t_ref_s + np.asarray(beam_offsets_s, dtype=np.float64))
    ref = history.poses_at(np.array([t_ref_s]))[0]
    motion = relative(ref, poses)
    motion[:, 2] = heading_scale * (poses[:, 2] - ref[2])
    if np.abs(motion[:, :2]).max() < STILL_M and np.abs(motion[:, 2]).max() < STILL_RAD:
        return None
    return motion


def beam_time_offsets_s(num_beams: int, time_increment_s: float | None) -> np.ndarray | None:
    """(num_beams,) each beam's time relative to the middle beam [s]; None without a time increment."""
    if not time_increment_s:
        return None
    return (np.arange(num_beams) - (num_beams - 1) / 2.0) * float(time_increment_s)


class TimeOffsetEstimator:
    """Online estimate of the LiDAR-to-odometry time offset (module docstring).

    ``fixed_s``: a configured offset, always applied (the estimate is still made and reported);
    None: apply the estimate once confident. ``max_abs_s``: candidates lie within +-this;
    ``prior_weight`` [rad^2/s^2]: weight of the prior 'offset = 0'; ``loss_cap_rad``: residuals
    beyond this count as this (failed matches); ``band_s``: dead band; ``max_se_s``: the standard
    error below which the estimate is used; ``min_steps``: steps measured before it is used;
    ``min_evidence``: how much lower the cost at the estimate must be than at offset 0, in units of
    the mean squared residual (a chi-square with one degree of freedom, but the residuals are not
    independent: intel's odometry, which has no offset, reaches 21 along the way, exp2's 80 after 20
    steps); ``enabled``: False estimates nothing."""

    def __init__(self, fixed_s: float | None = None, max_abs_s: float = 0.3, prior_weight: float = 0.05,
                 loss_cap_rad: float = 0.15, band_s: float = 0.02, max_se_s: float = 0.02, min_steps: int = 10,
                 min_evidence: float = 50.0, enabled: bool = True):
        self.fixed_s = None if fixed_s is None else float(fixed_s)
        self.max_abs_s = float(max_abs_s)
        self.enabled = bool(enabled)
        self.loss_cap_rad = float(loss_cap_rad)
        self.band_s = float(band_s)
        self.max_se_s = float(max_se_s)
        self.min_steps = int(min_steps)
        self.min_evidence = float(min_evidence)
        n = int(round(self.max_abs_s / GRID_STEP_S))
        self.candidates_s = np.arange(-n, n + 1) * GRID_STEP_S
        self.prior_weight = float(prior_weight)
        self._cost = self.prior_weight * self.candidates_s ** 2
        self._pending: deque[tuple[float, float | None, float, float, float]] = deque()
        self._last_profile: np.ndarray | None = None
        self.steps_used = 0
        self.estimate_s = 0.0
        self.standard_error_s: float | None = None
        self.evidence = 0.0
        self._confident = False
        self.applied_changes = 0
        self._applied_s = self.fixed_s if self.fixed_s is not None else 0.0

    @property
    def applied_s(self) -> float:
        """The offset the filter pairs scans with now [s]."""
        return self._applied_s

    def record_step(self, t_s: float, measured_turn_rad: float | None, distance_m: float = 0.0,
                    heading_scale: float = 1.0, drift_rad_per_m: float = 0.0) -> None:
        """One processed scan stamped ``t_s``: the true turn since the previous processed scan as its
        accepted matches measured it (None: not measured; the scan still anchors the next step), the
        odometry's distance over the step and the heading calibration's scale and drift."""
        if self.enabled and len(self.candidates_s) > 1:
            self._pending.append((float(t_s), measured_turn_rad, float(distance_m), float(heading_scale),
                                  float(drift_rad_per_m)))

    def update(self, history: OdometryHistory, final: bool = False) -> None:
        """Evaluate the recorded steps that the odometry in ``history`` now covers (all of them when
        ``final``: the odometry has ended) and renew the estimate."""
        latest = history.t_latest
        if latest is None:
            return
        changed = False
        while self._pending and (final or self._pending[0][0] + self.max_abs_s <= latest):
            t_s, turn, distance, scale, drift = self._pending.popleft()
            profile = history.headings_at(t_s + self.candidates_s)
            previous, self._last_profile = self._last_profile, profile
            if turn is None or previous is None:
                continue
            predicted = scale * (profile - previous) + drift * distance
            residual = turn - predicted
            self._cost = self._cost + np.minimum(residual ** 2, self.loss_cap_rad ** 2)
            self.steps_used += 1
            changed = True
        if changed:
            self._estimate()

    def _estimate(self) -> None:
        cost = self._cost
        j = int(np.argmin(cost))
        h = GRID_STEP_S
        estimate = float(self.candidates_s[j])
        if 0 < j < len(cost) - 1:
            curvature = cost[j - 1] - 2 * cost[j] + cost[j + 1]
            if curvature > 0:
                estimate += h * float(np.clip(0.5 * (cost[j - 1] - cost[j + 1]) / curvature, -0.5, 0.5))
        self.estimate_s = estimate
        k = CURVATURE_STEPS
        self.standard_error_s = None
        noise = max(float(cost[j] - self.prior_weight * self.candidates_s[j] ** 2), 1e-12) / max(self.steps_used, 1)
        if k <= j < len(cost) - k and self.steps_used > 1:
            curvature = (cost[j - k] - 2 * cost[j] + cost[j + k]) / (k * h) ** 2  # d2 cost / d offset2
            if curvature > 0:
                self.standard_error_s = float(np.sqrt(2.0 * noise / curvature))
        # how much better the estimate explains the turns than no offset, in units of the residual noise
        # (a chi-square with one degree of freedom; the cost may have several minima, which the local
        # standard error alone does not see)
        zero = len(cost) // 2
        self.evidence = float(cost[zero] - cost[j]) / noise if self.steps_used > 1 and noise > 0 else 0.0
        # once applied, an estimate stays until its evidence falls below half the threshold (no toggling)
        needed = self.min_evidence * (0.5 if self._applied_s != 0.0 and self.fixed_s is None else 1.0)
        self._confident = (self.standard_error_s is not None and self.standard_error_s <= self.max_se_s
                           and self.steps_used >= self.min_steps and self.evidence >= needed)
        if self.fixed_s is None:
            significant = abs(estimate) >= max(self.band_s, SIGNIFICANT_SE * (self.standard_error_s or np.inf))
            applied = round(estimate / h) * h if self._confident and significant else 0.0
            if applied != self._applied_s:
                self.applied_changes += 1
            self._applied_s = applied

    def summary(self) -> dict:
        """What run.json reports: the estimate, its standard error, what was applied, and the steps."""
        return {"enabled": self.enabled, "mode": "auto" if self.fixed_s is None else "fixed",
                "estimated_s": round(self.estimate_s, 4) if self.steps_used else None,
                "standard_error_s": None if self.standard_error_s is None else round(self.standard_error_s, 4),
                "evidence": round(self.evidence, 1), "confident": self._confident,
                "applied_s": round(self._applied_s, 4),
                "applied_changes": self.applied_changes, "steps_used": self.steps_used,
                "search_s": [round(float(self.candidates_s[0]), 4), round(float(self.candidates_s[-1]), 4)]}


def matched_turn(before: np.ndarray, after: np.ndarray, accepted: np.ndarray,
                 min_accepted_share: float = 0.5) -> float | None:
    """The step's true turn [rad] as the accepted matches measured it: the mean heading change of
    the accepted particles (N, 3) ``before`` -> ``after``; None when fewer than ``min_accepted_share``
    of them were accepted."""
    if len(accepted) == 0 or accepted.mean() < min_accepted_share:
        return None
    return float(np.mean(wrap_angle(after[accepted, 2] - before[accepted, 2])))
