"""``map_points.ply``: the map as a point cloud, for Open3D, CloudCompare, PCL or MeshLab.

Every returned end point of the key frames' scans, placed at the key frames' optimised poses (map
frame, metres; z = 0: a planar scanner), then filtered as Open3D's ``voxel_down_sample`` and
``remove_statistical_outlier`` do (the same points; done here with numpy and SciPy's k-d tree, which a
run has loaded already, instead of importing Open3D: 0.5-0.8 s and 45-70 MB more per run):

- a voxel grid of the map's cell size: one point (the centroid) per occupied voxel, so a wall seen
  from a thousand poses is not a thousand copies of itself;
- statistical outlier removal: a point much farther from its :data:`OUTLIER_NEIGHBOURS` nearest
  neighbours than points usually are (:data:`OUTLIER_STD_RATIO` standard deviations) is dropped.
  On aces-rough it drops 3.6 % of the points, 69 % of them off the map's occupied cells against
  14 % of those it keeps (passers-by, stray returns).

Binary little-endian PLY with x, y, z as doubles (``plyfile``), points in voxel order (x, then y).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_engine.model.map_bundle import MapBundle
from slam_engine.products.files import atomic_path

POINT_CLOUD_FILE = "map_points.ply"
OUTLIER_NEIGHBOURS = 20
OUTLIER_STD_RATIO = 2.0
QUERY_CHUNK = 32768  # points whose neighbours are looked up at once (their distances and indices: 10 MB)


def map_points(bundle: MapBundle) -> np.ndarray:
    """(N, 2) every key frame's returned end points in the map frame [m] (before any filter)."""
    points = []
    for k in range(len(bundle)):
        hits = bundle.hits(k)
        x, y, theta = bundle.poses[k]
        c, s = np.cos(theta), np.sin(theta)
        points.append(np.column_stack([x + c * hits[:, 0] - s * hits[:, 1], y + s * hits[:, 0] + c * hits[:, 1]]))
    return np.concatenate(points) if points else np.zeros((0, 2))


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M, 2) the centroid of the ``points`` [m] in each occupied square voxel of side ``voxel_m``,
    voxels counted from half a voxel below the points' minimum (Open3D's ``voxel_down_sample``);
    sorted by voxel (x index, then y index)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    ix, iy = np.floor((points - (points.min(axis=0) - voxel_m * 0.5)) / voxel_m).astype(np.int64).T
    _, of_point, counts = np.unique(ix * (iy.max() + 1) + iy, return_inverse=True, return_counts=True)
    sums = [np.bincount(of_point, weights=points[:, axis]) for axis in (0, 1)]  # in point order, as Open3D adds
    return np.column_stack(sums) / counts[:, None]


def without_statistical_outliers(points: np.ndarray, neighbours: int = OUTLIER_NEIGHBOURS,
                                 std_ratio: float = OUTLIER_STD_RATIO) -> np.ndarray:
    """The ``points`` (N, 2) [m] whose mean distance to their ``neighbours`` nearest points (itself
    included) is above 0 and below the mean of those distances plus ``std_ratio`` standard deviations
    (Open3D's ``remove_statistical_outlier``); order kept. Fewer than ``neighbours`` + 1 points:
    all of them."""
    from scipy.spatial import cKDTree  # imported when used (numba has loaded scipy.linalg already)

    if len(points) <= neighbours:
        return points
    tree = cKDTree(points)
    mean_distance = np.empty(len(points))
    for start in range(0, len(points), QUERY_CHUNK):  # in pieces: all the neighbours at once took 64 MB
        distances, _ = tree.query(points[start:start + QUERY_CHUNK], k=neighbours, workers=-1)
        # summed in order, as Open3D does
        mean_distance[start:start + QUERY_CHUNK] = np.cumsum(distances, axis=1)[:, -1] / neighbours
    spaced = mean_distance > 0  # a point with its neighbours all on it counts, but adds nothing
    cloud_mean = mean_distance[spaced].sum() / len(points)
    std = np.sqrt(np.sum((mean_distance[spaced] - cloud_mean) ** 2) / (len(points) - 1))
    return points[spaced & (mean_distance < cloud_mean + std_ratio * std)]


def map_point_cloud(bundle: MapBundle, voxel_m: float | None = None) -> np.ndarray:
    """(N, 3) the filtered cloud [m] (z = 0): voxel size ``voxel_m`` (default: the map's cell size),
    then statistical outlier removal."""
    points = without_statistical_outliers(voxel_centroids(map_points(bundle), voxel_m or bundle.resolution_m))
    return np.column_stack([points, np.zeros(len(points))])


def write_map_point_cloud(bundle: MapBundle, path: str | Path, voxel_m: float | None = None) -> Path:
    """Write :func:`map_point_cloud` as a binary little-endian PLY (x, y, z doubles); returns the path."""
    from plyfile import PlyData, PlyElement  # imported when used

    cloud = map_point_cloud(bundle, voxel_m)
    vertices = np.empty(len(cloud), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    vertices["x"], vertices["y"], vertices["z"] = cloud.T
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<").write(tmp)
    return Path(path)
