"""The vehicle's exact motion along a world's route: corners rounded with arcs, a speed profile that
respects lateral and longitudinal acceleration limits, sampled densely in arc length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Motion:
    """Ground-truth motion sampled along the path: ``t_s``, ``x_m``, ``y_m``, ``theta_rad``
    (unwrapped), ``s_m`` (arc length). States at other times are interpolated."""

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    theta_rad: np.ndarray
    s_m: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x_m, y_m, theta_rad unwrapped, s_m) at times ``t_s`` (held at the ends)."""
        return tuple(np.interp(t_s, self.t_s, v) for v in (self.x_m, self.y_m, self.theta_rad, self.s_m))

    def yaw_rate_at(self, t_s: np.ndarray) -> np.ndarray:
        """Yaw rate [rad/s] at ``t_s`` (finite differences of the dense samples)."""
        rate = np.gradient(self.theta_rad, self.t_s)
        return np.interp(t_s, self.t_s, rate)

    def kidnapped(self, at_s: float, skip_s: float) -> tuple[Motion, Motion]:
        """The vehicle carried off ``at_s`` seconds into the drive to where it would have been ``skip_s``
        later, then driving on from there: (where it truly is, what its wheels and gyro feel: the same
        motion without the jump, continuing from where it was taken)."""
        t0 = self.t_s[0]
        before = self.t_s < t0 + at_s
        after = self.t_s >= t0 + at_s + skip_s
        t = np.concatenate([self.t_s[before], self.t_s[after] - skip_s])
        x, y, theta, s = self.at(np.array([t0 + at_s, t0 + at_s + skip_s]))
        true = Motion(t, *(np.concatenate([v[before], v[after]]) for v in (self.x_m, self.y_m, self.theta_rad,
                                                                          self.s_m)))
        turn = theta[0] - theta[1]
        c, s_turn = np.cos(turn), np.sin(turn)
        dx, dy = self.x_m[after] - x[1], self.y_m[after] - y[1]
        felt = Motion(t, np.concatenate([self.x_m[before], x[0] + c * dx - s_turn * dy]),
                      np.concatenate([self.y_m[before], y[0] + s_turn * dx + c * dy]),
                      np.concatenate([self.theta_rad[before], self.theta_rad[after] + turn]),
                      np.concatenate([self.s_m[before], self.s_m[after] - (s[1] - s[0])]))
        return true, felt

    def truncated(self, max_duration_s: float) -> Motion:
        """The first ``max_duration_s`` seconds."""
        keep = self.t_s <= self.t_s[0] + max_duration_s
        return Motion(*(v[keep] for v in (self.t_s, self.x_m, self.y_m, self.theta_rad, self.s_m)))


def rounded_path(route: np.ndarray, radius_m: float, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) every ~``step_m`` along the route with each corner replaced by a circular arc of
    ``radius_m`` (smaller where the legs are short), and the heading (N,) unwrapped [rad]."""
    pts = np.asarray(route, dtype=np.float64)
    pieces: list[np.ndarray] = []
    headings: list[np.ndarray] = []
    current = pts[0]
    for k in range(1, len(pts)):
        a, b = pts[k - 1], pts[k]
        leg_dir = (b - a) / np.linalg.norm(b - a)
        heading = np.arctan2(leg_dir[1], leg_dir[0])
        end, arc = b, None
        if k + 1 < len(pts):
            nxt = pts[k + 1] - b
            turn = np.arctan2(leg_dir[0] * nxt[1] - leg_dir[1] * nxt[0], leg_dir @ nxt)
            if abs(turn) > 1e-6:
                limit = 0.45 * min(np.linalg.norm(b - a), np.linalg.norm(nxt))
                r = min(radius_m, limit / np.tan(abs(turn) / 2))
                tangent = r * np.tan(abs(turn) / 2)
                end = b - leg_dir * tangent
                arc = (end, heading, turn, r)
        length = np.linalg.norm(end - current)
        n = max(int(np.ceil(length / step_m)), 1)
        f = np.arange(n)[:, None] / n
        pieces.append(current + f * (end - current))
        headings.append(np.full(n, heading))
        current = end
        if arc is not None:
            start, h0, turn, r = arc
            n = max(int(np.ceil(r * abs(turn) / step_m)), 1)
            h = h0 + turn * np.arange(n) / n
            sign = np.sign(turn)
            cx, cy = start[0] - sign * r * np.sin(h0), start[1] + sign * r * np.cos(h0)
            pieces.append(np.column_stack([cx + sign * r * np.sin(h), cy - sign * r * np.cos(h)]))
            headings.append(h)
            current = np.array([cx + sign * r * np.sin(h0 + turn), cy - sign * r * np.cos(h0 + turn)])
    pieces.append(current[None, :])
    headings.append(headings[-1][-1:])
    return np.concatenate(pieces), np.unwrap(np.concatenate(headings))


def drive_route(route: np.ndarray, cruise_speed_m_s: float, turn_radius_m: float, lateral_accel_m_s2: float,
                accel_m_s2: float, step_m: float, still_s: float = 1.0) -> Motion:
    """Motion along ``route``: start and stop at rest, ``still_s`` seconds standing still first."""
    xy, theta = rounded_path(route, turn_radius_m, step_m)
    ds = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    curvature = np.abs(np.gradient(theta, s, edge_order=1))
    v_limit = np.minimum(cruise_speed_m_s, np.sqrt(lateral_accel_m_s2 / np.maximum(curvature, 1e-9)))
    v = v_limit.copy()
    v[0] = v[-1] = 0.0
    for i in range(1, len(v)):  # forward pass: accelerate no faster than accel_m_s2
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * accel_m_s2 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):  # backward pass: brake in time
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * accel_m_s2 * ds[i]))
    dt = 2 * ds / np.maximum(v[1:] + v[:-1], 1e-9)
    t = still_s + np.concatenate([[0.0], np.cumsum(dt)])
    # Prepend the standing-still interval.
    t = np.concatenate([[0.0], t])
    xy = np.vstack([xy[:1], xy])
    theta = np.concatenate([theta[:1], theta])
    s = np.concatenate([[0.0], s])
    return Motion(t_s=t, x_m=xy[:, 0], y_m=xy[:, 1], theta_rad=theta, s_m=s)
