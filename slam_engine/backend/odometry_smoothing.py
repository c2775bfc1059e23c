"""Keep precise odometry's local precision in the final trajectory.

The front end places every key frame by a scan match: globally consistent, but each pose carries the
match's own white noise (centimetres outdoors at long range). A fibre-optic gyro with good wheel
encoders is far more precise than that from one key frame to the next, and the match noise would
replace its precision. How precise each source is, is measured on the log itself
(:func:`slam_engine.frontend.odometry_noise.estimate_noise`). The final poses then solve a small
pose graph: each key frame held at its optimised pose with sd_match, consecutive key frames tied by
the odometry increment with sd_odometry. Where odometry is the worse source (wheels alone, rough
odometry) the fit says so and the poses stay as they were; where it is the better one, the
trajectory follows it locally and the matches globally.
"""

from __future__ import annotations

import numpy as np

from slam_engine.backend.pose_graph import poses_of
from slam_engine.frontend.odometry_noise import NoiseEstimate
from slam_engine.model.poses import relative


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
    return poses_of(gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize(),
                    len(poses))
