"""Front-end steps checked against the key frames just before them, before loop closing.

The particle filter's best particle carries, here and there, a step whose heading is off by a tenth
of a radian or more and stays off: its scan was fitted to the particle's map in a wrong way, or the
particle that survived had kept its motion sample. Outdoors that happens where a scan sees little
that the last ones saw (turns between trees and cars): on the Freiburg campus 30-45 of about 2000
steps are off by more than 0.1 rad, indoors about one. Each such step bends the submap it falls in,
so a revisit matches the submap at a pose turned as much, and the heading error it leaves is what the
loop closures must then take out.

:func:`rematch_steps` walks the key frames in time order. Each key frame's scan (end points within
``match_range_m``) is scored at the pose the front end's step puts it, on a blurred hit grid of the
``rematch_key_frames`` key frames before it as placed so far. A scan that fits there below
``rematch_below_score`` is searched for within ``rematch_window_m`` / ``rematch_window_rad``; the
pose found replaces the step when it scores at least ``rematch_min_score`` and ``rematch_gain`` more
than the step's, and no pose farther than ``REMATCH_AMBIGUITY_M`` / ``REMATCH_AMBIGUITY_RAD`` scores
within ``runner_up_ratio`` of it. Every later key frame follows by the front end's steps from there.

Against a map of the key frames before placed by the ground truth, the pose found is within 0.04 rad
of the true heading at 37 of 39 such steps of campus seed 0, even where it scores as little as 0.2:
a scan holds its heading where its position along a wall or hedge is loose.

A key frame whose front-end match was rejected (an *unverified* step: the particle kept its motion
sample) is searched for whatever its step scores. The original Freiburg 079 log's odometry drives
forward where the robot backs up (its poses advance while its ``tv`` reads -0.5 m/s), 0.3-0.65 m off
per key frame; its scans still fit the key frames before them at 0.3 and more along the corridors,
so only a search finds the true step (docs/engine.md, "Steps checked before loop closing").

The check takes what outdoors gives it: scans with as few as ``REMATCH_MIN_POINTS`` returns and fits
scoring ``rematch_min_score`` (the steps the campus's front end turns are mostly such scans;
measurements in docs/engine.md, "Sparse scans and weak fits").
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slam_engine.backend.correlative import MatchGrid, angular_step_rad, refine_pose, search
from slam_engine.backend.submaps import match_grid_from_points
from slam_engine.config import LoopClosingConfig
from slam_engine.model.poses import compose, place_points, relative

# a second pose this far from the best [m] or in heading [rad], scoring within runner_up_ratio of it,
# makes the search ambiguous: the step is kept
REMATCH_AMBIGUITY_M, REMATCH_AMBIGUITY_RAD = 0.5, 0.2
# a key frame is rematched with at most this many of its end points, against at least this many (outdoors
# the scans whose steps the front end turns have 14-29 within match_range_m)
REMATCH_MAX_POINTS, REMATCH_MIN_POINTS = 250, 12
PYRAMID_LEVELS = 6  # blocks up to 32 cells: the window is at most a few tens of cells wide


@dataclass
class StepRematch:
    """The key frames' poses (K, 3, world frame) after the check, and the key frames whose step from
    the one before was replaced, each with the step's score and the replacing pose's; how many of
    those the front end had left unverified."""

    path: np.ndarray
    replaced: list[tuple[int, float, float]] = field(default_factory=list)
    unverified_replaced: int = 0

    def summary(self) -> dict:
        return {"steps_replaced": len(self.replaced), "unverified_steps_replaced": self.unverified_replaced}


def _thin(points: np.ndarray, budget: int) -> np.ndarray:
    if len(points) <= budget:
        return points
    return points[np.linspace(0, len(points) - 1, budget).astype(np.int64)]


def rematch_steps(path: np.ndarray, points_v: list[np.ndarray], config: LoopClosingConfig, resolution_m: float,
                  threads: int = 1, unverified: np.ndarray | None = None) -> StepRematch:
    """Key-frame poses ``path`` (K, 3) with the steps that fit the key frames before them poorly replaced
    by a better fit (module docstring); ``points_v``: each key frame's end points (B, 2) [m, vehicle frame].
    ``unverified`` (K,): the key frames whose front-end match was rejected, each searched for whatever
    its step scores (with ``config.rematch_unverified``). Nothing is replaced when loop closing or
    ``config.rematch_steps`` is off."""
    path = np.asarray(path, np.float64)
    out = StepRematch(path=path.copy())
    if not (config.enabled and config.rematch_steps) or len(path) < 2:
        return out
    c = config
    near = [p[np.hypot(p[:, 0], p[:, 1]) <= c.match_range_m] for p in points_v]
    poses = out.path
    before: deque[np.ndarray] = deque([place_points(poses[0], near[0])], maxlen=c.rematch_key_frames)
    always = np.zeros(len(path), bool)
    if unverified is not None and c.rematch_unverified:
        always = np.asarray(unverified, bool)
    for k in range(1, len(path)):
        predicted = compose(poses[k - 1], relative(path[k - 1], path[k]))
        scan = _thin(near[k], REMATCH_MAX_POINTS)
        found = _better_fit(scan, predicted, np.concatenate(before), c, resolution_m, threads, bool(always[k]))
        if found is None:
            poses[k] = predicted
        else:
            poses[k] = found[0]
            out.replaced.append((k, found[1], found[2]))
            out.unverified_replaced += int(always[k])
        before.append(place_points(poses[k], near[k]))
    return out


def _better_fit(scan: np.ndarray, predicted: np.ndarray, map_points: np.ndarray, c: LoopClosingConfig,
                resolution_m: float, threads: int, always: bool = False) -> tuple[np.ndarray, float, float] | None:
    """The pose that replaces ``predicted`` for ``scan`` (B, 2) [m, vehicle frame] on the map of
    ``map_points`` (N, 2) [m, world frame], with the scores of both; None to keep ``predicted``.
    ``always``: searched even where the step's pose scores ``rematch_below_score`` or more."""
    if len(scan) < REMATCH_MIN_POINTS or len(map_points) < REMATCH_MIN_POINTS:
        return None
    # one level: the check at the step's pose searches one cell and angular step around it
    grid = match_grid_from_points(map_points, resolution_m, margin_m=1.0, n_levels=1)
    here = search(grid, scan, predicted, resolution_m, angular_step_rad(scan, resolution_m), 0.0)
    step_score = 0.0 if here is None else here.score
    if step_score >= c.rematch_below_score and not always:
        return None
    grid = MatchGrid.from_values(grid.values, grid.origin_m, resolution_m, PYRAMID_LEVELS)
    best = search(grid, scan, predicted, c.rematch_window_m, c.rematch_window_rad, c.rematch_min_score,
                  ambiguity_m=REMATCH_AMBIGUITY_M, ambiguity_rad=REMATCH_AMBIGUITY_RAD,
                  runner_up_share=c.runner_up_ratio, runner_up_min_score=0.0, threads=threads)
    if (best is None or best.score < step_score + c.rematch_gain
            or best.runner_up_score >= c.runner_up_ratio * best.score):
        return None
    return refine_pose(grid, scan, best.pose), round(step_score, 4), round(best.score, 4)
