"""How far a finished map contradicts the scans it was made of (no ground truth needed).

Each key frame's returns, at the key frame's final pose, should fall on cells the map holds occupied.
Where the map holds them *free*, other scans saw through that place: the map contradicts the scan. Some
contradicted returns are normal (people, doors, parked cars gone on the next pass, foliage and glass seen
through, a wall's far side at a slant); a key frame with many of them lies where the rest of the map
disagrees, as in a map whose parts are offset or turned against each other where they overlap.

Measured on the benchmark logs (2026-11-27, seeds 0-2, the product map), the share of key frames with
more than ``CONTRADICTED_SHARE`` of their returns on free cells: intel 0-0.1 %, freiburg-079 0.2-3.2 %,
aces-rough 0.2-0.5 %, infinite-corridor-rough 0.5-0.9 %, malaga 2.2-7.7 %, exp2 and the simulated car
0 % (maps that hold), and 37-56 % on freiburg-campus-rough (lost: relation error 38-80 m). On the
original logs with real odometry (2026-11-29, seeds 0-4): Intel 0.5-0.7 % and Freiburg 079 2.1-3.7 %
where they map at 0.017-0.021 and 0.046-0.048 m; 10-20 % where they broke (0.30-2.0 m). A map is
*flagged* above ``FLAG_SHARE`` (0.15 before 2026-11-29 missed Freiburg 079's broken maps at 10.4-11.8 %);
a run then tries the back end's alternatives (:mod:`slam_engine.backend.flagged_retry`). The measure
sees breaks only where the parts overlap, and mildly: the simulated office with the second half of its
drive turned 0.1 rad or shifted 1 m against the first comes to 4.5-5.6 % (0 % as mapped), within what
real clutter gives a sound map, and is not flagged.

Free is what ``map.pgm`` shows as free (:data:`~slam_engine.products.rendering.FREE_THRESHOLD`).
Poses ``[x_m, y_m, theta_rad]`` in the map frame; returns (B, 2) [m] in the vehicle frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slam_engine.model.poses import place_each
from slam_engine.model.result import OccupancyGrid
from slam_engine.products.rendering import FREE_THRESHOLD

CONTRADICTED_SHARE = 0.3  # a key frame with more of its returns than this on free cells is contradicted
FLAG_SHARE = 0.08  # a map with a larger share of contradicted key frames is flagged
MIN_RETURNS = 10  # a key frame with fewer returns on the map is not judged
WARNING_START = "the map contradicts its own scans"  # how MapConsistency.warning() begins


@dataclass(frozen=True)
class MapConsistency:
    """``returns_on_free``: the share of every key frame's returns that fall on free cells;
    ``contradicted``: how many of the ``judged`` key frames (those with at least ``MIN_RETURNS`` returns
    on the map) have more than ``CONTRADICTED_SHARE`` of theirs there."""

    returns_on_free: float
    judged: int
    contradicted: int

    @property
    def contradicted_share(self) -> float:
        return self.contradicted / self.judged if self.judged else 0.0

    @property
    def flagged(self) -> bool:
        """Whether so many key frames are contradicted that the map is probably broken."""
        return self.contradicted_share > FLAG_SHARE

    def as_dict(self) -> dict:
        return {"flagged": self.flagged, "returns_on_free_share": round(self.returns_on_free, 4),
                "key_frames_judged": self.judged, "key_frames_contradicted": self.contradicted,
                "key_frames_contradicted_share": round(self.contradicted_share, 4),
                "contradicted_above_share": CONTRADICTED_SHARE,
                "flagged_above_share": FLAG_SHARE}

    def warning(self) -> str | None:
        """One line for the run's warnings when the map is :attr:`flagged`, else None."""
        if not self.flagged:
            return None
        return (f"{WARNING_START}: {self.contradicted} of {self.judged} key frames "
                f"({100 * self.contradicted_share:.0f} %) have more than {100 * CONTRADICTED_SHARE:.0f} % of their "
                "returns where other scans saw free space: parts of the map are probably offset or turned "
                "against each other (drift the loop closing could not correct: see run.json's loop_closing), "
                "unless the scene changed between passes or was seen through")


def map_consistency(grid: OccupancyGrid, poses: np.ndarray, returns_v: Sequence[np.ndarray]) -> MapConsistency:
    """:class:`MapConsistency` of ``grid`` with the key frames at ``poses`` (K, 3) and their returns
    ``returns_v`` (K arrays (B, 2))."""
    counts = np.array([len(r) for r in returns_v], np.int64)
    if len(poses) != len(returns_v):
        raise ValueError(f"map_consistency: {len(poses)} poses, {len(returns_v)} key frames of returns")
    if counts.sum() == 0:
        return MapConsistency(0.0, 0, 0)
    owner = np.repeat(np.arange(len(counts)), counts)
    points = place_each(np.asarray(poses, np.float64), np.concatenate(returns_v), owner)
    ix, iy = grid.world_to_cell(points[:, 0], points[:, 1])
    rows, cols = grid.shape
    inside = (ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)
    free_log_odds = math.log(FREE_THRESHOLD / (1.0 - FREE_THRESHOLD))
    values = grid.log_odds[iy[inside], ix[inside]]
    on_free = (values != 0.0) & (values < free_log_odds)
    on_map = np.bincount(owner[inside], minlength=len(counts))
    free = np.bincount(owner[inside], weights=on_free, minlength=len(counts))
    judged = on_map >= MIN_RETURNS
    contradicted = judged & (free > CONTRADICTED_SHARE * on_map)
    return MapConsistency(float(on_free.mean()) if on_free.size else 0.0, int(judged.sum()), int(contradicted.sum()))
