"""Align each key frame to the map of all of them: the last pass of the back end.

After the pose graph, every key frame's pose still carries its own front-end error: the scan match
against the particle's map at that moment, and the proposal's draw around it. The map of all key
frames at their optimised poses averages those errors away. Each key frame's scan is fitted onto
that map (a blurred hit grid, :func:`~slam_engine.backend.submaps.match_grid_from_points`; sub-cell
Levenberg-Marquardt, :func:`~slam_engine.backend.correlative.refine_poses`), the map is re-rendered
from the fitted poses and the scans fitted again (``passes``).

The fits and the graph's poses are then combined by least squares
(:func:`slam_engine.backend.odometry_smoothing.smooth_with_odometry`): each key frame held at its fit,
consecutive ones tied by the graph's increments. How precise a fit is, is measured on the scans
themselves (:func:`fit_noise`: each scan's even and odd end points fitted apart); the difference
between the fits and the graph's poses (:func:`slam_engine.frontend.odometry_noise.estimate_noise`) holds
that noise, the graph poses' own and their drift, so what is left of it is the graph's. (Measuring
both from the difference alone cannot tell whose the white noise is: it trusted the graph and
left a 2 cm jitter in place.)

Replayed on the shared logs' recorded front ends, seeds 0-4, three passes, relation error median /
worst [m]: intel 0.0250 / 0.0266 -> 0.0214 / 0.0225, freiburg-079 0.0211 / 0.0247 -> 0.0197 /
0.0231, aces-rough 0.0438 / 0.0440 -> 0.0392 / 0.0392, infinite-corridor-rough 0.0469 / 0.0499 ->
0.0436 / 0.0456. Fitted poses alone (no combination) cost freiburg-079 its local precision
(0.0063 -> 0.0094 m).
"""

from __future__ import annotations

import math

import numpy as np

from slam_engine.backend.correlative import refine_poses
from slam_engine.backend.odometry_smoothing import smooth_with_odometry
from slam_engine.backend.submaps import match_grid_from_points
from slam_engine.frontend.odometry_noise import (
    MAD_TO_SD,
    MATCH_SD_FLOOR,
    ODOMETRY_SD_FLOOR,
    NoiseEstimate,
    estimate_noise,
)
from slam_engine.model.poses import place_points, point_bounds, wrap_angle

# a key frame needs this many end points to be fitted (fewer: it keeps its pose)
MIN_POINTS = 30
# empty border around the map's end points [m]
MARGIN_M = 1.0
# the map is built for runs of key frames whose end points fit in a box this wide [m]
CHUNK_M = 60.0


def _chunks(placed: np.ndarray, starts: np.ndarray, size_m: float) -> list[tuple[range, np.ndarray]]:
    """Runs of consecutive key frames whose end points (``placed`` (N, 2), world frame; key frame k's
    are rows ``starts[k]:starts[k + 1]``) fit in a box of ``size_m`` (a key frame alone may exceed
    it), each with its box [x_min, y_min, x_max, y_max] [m]."""
    counts = np.diff(starts)
    filled = np.flatnonzero(counts)
    lows = np.minimum.reduceat(placed, starts[filled], axis=0) if len(filled) else np.empty((0, 2))
    highs = np.maximum.reduceat(placed, starts[filled], axis=0) if len(filled) else np.empty((0, 2))
    out: list[tuple[range, np.ndarray]] = []
    first, box = 0, None
    for k, lo, hi in zip(filled.tolist(), lows.tolist(), highs.tolist(), strict=True):
        own = [*lo, *hi]  # [x_min, y_min, x_max, y_max]
        grown = own if box is None else [min(box[0], lo[0]), min(box[1], lo[1]), max(box[2], hi[0]),
                                         max(box[3], hi[1])]
        if box is not None and max(grown[2] - grown[0], grown[3] - grown[1]) > size_m:
            out.append((range(first, k), np.array(box)))
            first, grown = k, own
        box = grown
    if box is not None:
        out.append((range(first, len(counts)), np.array(box)))
    return out


def fit_to_map(poses: np.ndarray, points_v: list[np.ndarray], resolution_m: float,
               halves: bool = False) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(K, 3) each key frame's pose fitted onto the map of all key frames' end points ``points_v``
    (K lists of (B, 2) [m], vehicle frame) placed at ``poses`` (K, 3, world frame); key frames with
    fewer than ``MIN_POINTS`` end points keep their pose. With ``halves``, also the fits of each scan's
    even and of its odd end points alone (None otherwise; a scan with fewer than twice ``MIN_POINTS``
    keeps its pose in both). The map is built a stretch of key frames at a time (``CHUNK_M``
    across, from every end point within its reach): a whole building's would take gigabytes."""
    poses = np.asarray(poses, np.float64)
    counts = np.array([len(p) for p in points_v], np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    vehicle = np.concatenate(points_v) if len(points_v) else np.empty((0, 2))
    everything = np.empty_like(vehicle)
    for k, (pose, pts) in enumerate(zip(poses, points_v, strict=True)):
        everything[starts[k]:starts[k + 1]] = place_points(pose, pts)
    fitted = poses.copy()
    even = poses.copy() if halves else None
    odd = poses.copy() if halves else None
    reach = MARGIN_M + 3 * resolution_m  # every end point whose blur reaches a cell the fits read
    lowest, highest = point_bounds(everything) if len(everything) else (np.zeros(2), np.zeros(2))
    for nodes, box in _chunks(everything, starts, CHUNK_M):
        if (lowest >= box[:2] - reach).all() and (highest <= box[2:] + reach).all():
            near = everything
        else:
            near = everything[(everything[:, 0] >= box[0] - reach) & (everything[:, 0] <= box[2] + reach)
                              & (everything[:, 1] >= box[1] - reach) & (everything[:, 1] <= box[3] + reach)]
        grid = match_grid_from_points(near, resolution_m, MARGIN_M, n_levels=0)
        ks = np.arange(nodes.start, nodes.stop)
        chunk = counts[ks]
        fitted[ks] = refine_poses(grid, vehicle, starts, poses, ks[chunk >= MIN_POINTS])[ks]
        if even is not None and odd is not None:
            halved = ks[chunk >= 2 * MIN_POINTS]
            even[ks] = refine_poses(grid, vehicle, starts, poses, halved, first=0, step=2)[ks]
            odd[ks] = refine_poses(grid, vehicle, starts, poses, halved, first=1, step=2)[ks]
    return fitted, even, odd


def _robust_sd(values: np.ndarray) -> float:
    return MAD_TO_SD * float(np.median(np.abs(values - np.median(values)))) if len(values) else 0.0


def fit_noise(even: np.ndarray, odd: np.ndarray, points_v: list[np.ndarray]) -> tuple[float, float]:
    """A fit's own noise (sd per axis [m], heading sd [rad]), from the scans themselves: the fits of
    each scan's even and of its odd end points (:func:`fit_to_map`) differ by twice a half's
    variance, and a half (half the points) has twice the whole scan's."""
    both = np.array([len(p) >= 2 * MIN_POINTS for p in points_v], bool)
    d = even[both] - odd[both]
    sd_m = 0.5 * float(np.hypot(_robust_sd(d[:, 0]), _robust_sd(d[:, 1]))) / math.sqrt(2.0)
    return sd_m, 0.5 * _robust_sd(np.asarray(wrap_angle(d[:, 2])))


def align_to_map(poses: np.ndarray, points_v: list[np.ndarray], resolution_m: float, passes: int,
                 max_range_m: float) -> tuple[np.ndarray, dict]:
    """The key frames' ``poses`` (K, 3, world frame; the back end's) combined with their fits to the
    map (``passes`` fits, each onto the map of the last), and a summary for run.json. ``points_v``:
    each key frame's end points (B, 2) [m, vehicle frame]; those farther than ``max_range_m`` from
    the vehicle are left out (far points place a scan less precisely)."""
    poses = np.asarray(poses, np.float64)
    if passes < 1:
        return poses, {"applied": False, "reason": "disabled in the configuration"}
    points_v = [p[np.hypot(p[:, 0], p[:, 1]) <= max_range_m] for p in points_v]
    if not any(len(p) for p in points_v):
        return poses, {"applied": False, "reason": "no end points"}
    fitted, even, odd = poses, None, None
    for n in range(passes):
        fitted, even, odd = fit_to_map(fitted, points_v, resolution_m, halves=n == passes - 1)
    assert even is not None and odd is not None
    # graph poses - fits: both sources' fixed noise (a) and the graph's drift per step (b)
    difference = estimate_noise(fitted, poses)
    if difference is None:
        return poses, {"applied": False, "reason": "too few key frames to measure the fits' noise"}
    fit_sd_m, fit_sd_rad = fit_noise(even, odd, points_v)
    fit_sd_m, fit_sd_rad = max(fit_sd_m, MATCH_SD_FLOOR[0]), max(fit_sd_rad, MATCH_SD_FLOOR[1])
    # what is left of the fixed part is the graph poses' own: it enters each of their increments twice
    graph_m = max(difference.match_sd_m**2 - fit_sd_m**2, 0.0)
    graph_rad = max(difference.match_sd_rad**2 - fit_sd_rad**2, 0.0)
    noise = NoiseEstimate(match_sd_m=fit_sd_m, match_sd_rad=fit_sd_rad,
                          odometry_sd_m=max(float(np.sqrt(2.0 * graph_m + difference.odometry_sd_m**2)),
                                            ODOMETRY_SD_FLOOR[0]),
                          odometry_sd_rad=max(float(np.sqrt(2.0 * graph_rad + difference.odometry_sd_rad**2)),
                                              ODOMETRY_SD_FLOOR[1]))
    moved = np.hypot(*(fitted[:, :2] - poses[:, :2]).T)
    out = smooth_with_odometry(fitted, poses, noise)
    return out, {"applied": True, "passes": passes, "fit_sd_m": round(noise.match_sd_m, 5),
                 "fit_sd_rad": round(noise.match_sd_rad, 6), "graph_sd_m_per_step": round(noise.odometry_sd_m, 5),
                 "graph_sd_rad_per_step": round(noise.odometry_sd_rad, 6),
                 "median_fit_shift_m": round(float(np.median(moved)), 4)}
