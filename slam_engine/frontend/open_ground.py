"""Whether a drive is on open ground, where a level LiDAR's beams without a return are poor evidence
of free space.

In a building a beam returns nothing through a window, a glass door or off a black surface: 0-2.5 % of
the benchmark buildings' beams, 11.5 % on malaga's street. Clearing free space along them (to
``grid.no_return_clear_m``) helps the scan matcher there (intel and freiburg-079 are 10-15 % less accurate
without it). On the Freiburg campus a quarter of the beams return nothing (26 %; 52-68 % in its open
squares), and there they clear cells that the next pass hits (foliage, cars, people, the ground as the
robot pitches): over ten seeds the campus came to 0.76 m median and 1.66 m worst without that clearing,
against 0.94 / 8.93 m with it (docs/engine.md, Known weaknesses).

So a drive whose level LiDAR returned nothing on more than ``grid.no_return_open_share`` of its beams is
mapped with ``grid.no_return_clear_m`` 0. Its loops close from ``loop_closing.open_ground_min_score``
(0.5) rather than ``min_score`` (0.6): outdoors a revisit's scan scores about 0.5 at its true pose
(foliage, cars and people move; the 8 m submap saw less of what a long-range scan sees). With the
front end's steps checked first, the campus's ten seeds (replayed) came to 0.17 / 0.65 m (median /
worst) against 0.20 / 1.23 m at 0.6 (docs/engine.md, Known weaknesses).

This needs the whole drive before mapping: a batch run (:func:`slam_engine.pipeline.run_slam`); a live
job, which sees the drive as it comes, keeps the configured setting. A tilted LiDAR is left as it is: its
no-return beams already stop where they leave the height band.
"""

from __future__ import annotations

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.frontend.lidar_points import returned_beams
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.poses import is_planar_4x4


def no_return_share(log: DriveLog) -> float | None:
    """The share of the drive's beams that returned nothing within the LiDAR's range; None for a
    tilted LiDAR or a log without scans."""
    if log.scans is None or log.lidar is None or len(log.scans) == 0:
        return None
    if not is_planar_4x4(np.asarray(log.lidar.T_vehicle_from_lidar, np.float64)):
        return None
    returned = returned_beams(log.scans.ranges_m, log.lidar)
    return 1.0 - float(np.count_nonzero(returned)) / returned.size


def open_ground_config(config: SlamConfig, log: DriveLog) -> tuple[SlamConfig, dict]:
    """``config`` for mapping ``log``: with ``grid.no_return_clear_m`` 0, closures from
    ``loop_closing.open_ground_min_score``, the submap lengths
    ``loop_closing.open_ground_alternative_submap_lengths_m`` tried (where no alternatives are set) and
    unverified steps searched only where they fit poorly (``rematch_unverified`` off) and far searches
    over the whole map (``place_index.far_searches`` off) when the drive is on open ground, else as given;
    and what was decided, for run.json."""
    share = no_return_share(log)
    bar = config.grid.no_return_open_share
    summary = {"no_return_share": None if share is None else round(share, 4), "open_ground_above": bar,
               "open_ground": False}
    short_range = log.lidar is not None and log.lidar.range_max_m < config.grid.no_return_min_sensor_range_m
    if share is None or share <= bar or short_range:
        return config, summary  # (a short-range scanner's no-return beams clear nothing anyway)
    grid = config.grid.model_copy(update={"no_return_clear_m": 0.0})
    closing = config.loop_closing
    loop_closing = closing.model_copy(
        update={"min_score": min(closing.min_score, closing.open_ground_min_score), "rematch_unverified": False,
                "alternative_submap_lengths_m": (closing.alternative_submap_lengths_m
                                                 or closing.open_ground_alternative_submap_lengths_m)})
    places = config.place_index.model_copy(update={"far_searches": False})
    return (config.model_copy(update={"grid": grid, "loop_closing": loop_closing, "place_index": places}),
            {**summary, "open_ground": True})
