"""Camera points into the world: ``to_matrix_4x4(pose(t)) @ T_vehicle_from_camera`` with Open3D
point clouds, the trajectory interpolated at the image timestamp, and ground selection by height.

The trajectory is planar (SE(2)), so the world frame's z is the vehicle frame's z: heights are
metres above the vehicle frame's origin plane.
"""

from __future__ import annotations

import numpy as np

from slam_engine.model.poses import interpolate
from slam_engine.model.result import Trajectory


def interpolate_poses(trajectory: Trajectory, t_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 3) [x_m, y_m, theta_rad] at times ``t_s`` (:func:`slam_engine.model.poses.interpolate`) and
    a (N,) bool mask of the times within ``max_gap_s`` of the trajectory's span (outside it the
    nearest end pose is returned)."""
    t_s = np.asarray(t_s, dtype=np.float64)
    traj_t = np.asarray(trajectory.t_s, dtype=np.float64)
    valid = (t_s >= traj_t[0] - max_gap_s) & (t_s <= traj_t[-1] + max_gap_s)
    return interpolate(traj_t, trajectory.poses, t_s), valid


def transform_points(points: np.ndarray, T_to_from: np.ndarray) -> np.ndarray:
    """(N, 3) points [m] mapped by a 4x4 transform, as one Open3D point-cloud operation."""
    if len(points) == 0:
        return np.empty((0, 3))
    import open3d as o3d  # imported when used: ~85 MB that a run without cameras never needs

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.transform(np.asarray(T_to_from, dtype=np.float64))
    return np.asarray(cloud.points)


def ground_mask(points_world: np.ndarray, ground_z_m: float, band_m: float) -> np.ndarray:
    """(N,) bool: points within ``band_m`` of the ground height ``ground_z_m`` [m]."""
    return np.abs(points_world[:, 2] - ground_z_m) <= band_m


PLANE_REFITS = 10


def estimate_ground_z(points_vehicle: np.ndarray, max_tilt_rad: float = 0.25, distance_m: float = 0.05,
                      seed: int = 0) -> float | None:
    """Height [m] of the dominant near-horizontal plane below the cameras, fitted with Open3D's
    RANSAC ``segment_plane``; None when there are too few points or the best plane is tilted more
    than ``max_tilt_rad`` (a wall, say)."""
    points = np.asarray(points_vehicle, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 100:
        return None
    import open3d as o3d

    o3d.utility.random.seed(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if len(points) > 200_000:
        cloud = cloud.random_down_sample(200_000 / len(points))
    (a, b, c, d), _ = cloud.segment_plane(distance_threshold=distance_m, ransac_n=3, num_iterations=500)
    # RANSAC's plane depends on its random draws (seed, and the points sampled): refit it to its
    # inliers by least squares until they stop changing, so that the height depends on the ground only
    xyz = np.asarray(cloud.points)
    normal = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    offset = d / np.linalg.norm([a, b, c])
    inliers = np.zeros(len(xyz), dtype=bool)
    for _ in range(PLANE_REFITS):
        previous, inliers = inliers, np.abs(xyz @ normal + offset) <= distance_m
        if inliers.sum() < 50 or np.array_equal(inliers, previous):
            break
        centroid = xyz[inliers].mean(axis=0)
        normal = np.linalg.svd(xyz[inliers] - centroid, full_matrices=False)[2][-1]
        offset = -float(normal @ centroid)
    if abs(normal[2]) < np.cos(max_tilt_rad) or inliers.sum() < 50:
        return None
    # to 0.1 mm: the refits can settle on either of two inlier sets whose heights differ by ~1e-7 m
    return round(float(np.median(xyz[inliers, 2])), 4)
