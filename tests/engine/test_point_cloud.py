"""``map_points.ply``: the map as a point cloud, read back with Open3D as its users would, lies on
the map's occupied cells, one point per cell at most, stray returns removed."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest

from slam_engine import run_slam
from slam_engine.config import SlamConfig
from slam_engine.products import write_products
from slam_engine.products.point_cloud import (
    OUTLIER_NEIGHBOURS,
    OUTLIER_STD_RATIO,
    POINT_CLOUD_FILE,
    map_point_cloud,
    map_points,
)
from slam_engine.simulation import simulate


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    drive = simulate("office", seed=0, rig="carmen-robot", max_duration_s=60.0, cameras=False)
    result = run_slam(drive.log, SlamConfig(particles=8, seed=0))
    out = tmp_path_factory.mktemp("products")
    return result, write_products(result, out)


def near_occupied(points: np.ndarray, grid, cells: int = 1) -> np.ndarray:
    """(N,) bool: the point's cell or one within ``cells`` of it is occupied (log-odds > 0)."""
    ix, iy = grid.world_to_cell(points[:, 0], points[:, 1])
    ix, iy = np.asarray(ix, int), np.asarray(iy, int)
    h, w = grid.shape
    found = np.zeros(len(points), bool)
    for dx in range(-cells, cells + 1):
        for dy in range(-cells, cells + 1):
            cx, cy = ix + dx, iy + dy
            inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
            found[inside] |= grid.log_odds[cy[inside], cx[inside]] > 0
    return found


def test_the_point_cloud_lies_on_the_maps_occupied_cells(mapped) -> None:
    result, written = mapped
    cloud = o3d.io.read_point_cloud(str(written[POINT_CLOUD_FILE]))
    points = np.asarray(cloud.points)
    assert len(points) > 1000 and np.all(points[:, 2] == 0.0)
    on_map = near_occupied(points[:, :2], result.grid)
    assert on_map.mean() > 0.97, on_map.mean()
    # one point per voxel of the map's cell size: never more points than cells they fall in, and far
    # fewer than the scans' returns
    cells = {tuple(c) for c in np.floor(points[:, :2] / result.grid.resolution_m).astype(int)}
    assert len(points) <= 4 * len(cells)
    assert len(points) < len(map_points(result.bundle)) / 5
    assert POINT_CLOUD_FILE in written and POINT_CLOUD_FILE in written["run.json"].read_text()


def test_outlier_removal_drops_stray_points(mapped) -> None:
    """Stray returns added to the scans (a passer-by 1 m off a wall, single points in free space) are
    dropped by the statistical filter; the walls stay."""
    from scipy.ndimage import distance_transform_edt

    result, _ = mapped
    clean = map_point_cloud(result.bundle)[:, :2]
    rng = np.random.default_rng(0)
    metres_to_wall = distance_transform_edt(result.grid.log_odds <= 0) * result.grid.resolution_m
    free = np.argwhere((result.grid.log_odds < -2.0) & (metres_to_wall > 0.5))  # open floor
    stray_cells = free[rng.choice(len(free), 30, replace=False)]
    stray = np.column_stack([result.grid.origin_x_m + (stray_cells[:, 1] + 0.5) * result.grid.resolution_m,
                             result.grid.origin_y_m + (stray_cells[:, 0] + 0.5) * result.grid.resolution_m])
    # the stray points, given as returns of key frame 0 (vehicle frame = map frame through its pose)
    bundle = result.bundle
    x, y, theta = bundle.poses[0]
    c, s = np.cos(theta), np.sin(theta)
    dx, dy = stray[:, 0] - x, stray[:, 1] - y
    local = np.column_stack([c * dx + s * dy, -s * dx + c * dy])
    k0 = slice(int(bundle.scan_offsets[0]), int(bundle.scan_offsets[1]))
    bundle = dataclasses.replace(
        bundle, ends_v=np.concatenate([bundle.ends_v[k0], local.astype(np.float32), bundle.ends_v[k0.stop:]]),
        is_hit=np.concatenate([bundle.is_hit[k0], np.ones(len(local), bool), bundle.is_hit[k0.stop:]]),
        free_from_m=np.concatenate([bundle.free_from_m[k0], np.zeros(len(local), np.float32),
                                    bundle.free_from_m[k0.stop:]]),
        scan_offsets=bundle.scan_offsets + np.r_[0, np.full(len(bundle.scan_offsets) - 1, len(local))])
    assert len(map_points(bundle)) == len(map_points(result.bundle)) + len(local)
    noisy = map_point_cloud(bundle)[:, :2]
    kept_stray = sum(np.min(np.hypot(*(noisy - p).T)) < result.grid.resolution_m / 2 for p in stray)
    assert kept_stray <= 3, kept_stray  # of 30
    walls = near_occupied(noisy, result.grid).sum()
    assert walls >= near_occupied(clean, result.grid).sum() - 5  # the walls kept


def open3d_filtered(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) ``points`` (N, 2) through Open3D's own voxel grid and statistical outlier removal."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.column_stack([points, np.zeros(len(points))])))
    cloud = cloud.voxel_down_sample(voxel_m)
    cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=OUTLIER_NEIGHBOURS, std_ratio=OUTLIER_STD_RATIO)
    return np.asarray(cloud.points)


def sorted_rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_the_file_holds_the_points_open3d_filters_would_give(mapped) -> None:
    """The voxel grid and the outlier filter give Open3D's points exactly (in another order), and the
    PLY read back with Open3D holds them, as doubles."""
    result, written = mapped
    expected = open3d_filtered(map_points(result.bundle), result.bundle.resolution_m)
    assert len(expected) > 1000
    assert np.array_equal(sorted_rows(map_point_cloud(result.bundle)), sorted_rows(expected))
    read_back = np.asarray(o3d.io.read_point_cloud(str(written[POINT_CLOUD_FILE])).points)
    assert np.array_equal(sorted_rows(read_back), sorted_rows(expected))
    assert b"property double x" in written[POINT_CLOUD_FILE].read_bytes()[:200]


def test_neighbours_looked_up_in_pieces_give_the_same_points(mapped, monkeypatch) -> None:
    """The outlier filter's neighbour search runs a piece of the points at a time (memory): any piece
    size gives the same points as all at once."""
    from slam_engine.products import point_cloud

    result, _ = mapped
    voxels = point_cloud.voxel_centroids(map_points(result.bundle), result.bundle.resolution_m)
    monkeypatch.setattr(point_cloud, "QUERY_CHUNK", len(voxels) + 1)
    whole = point_cloud.without_statistical_outliers(voxels)
    monkeypatch.setattr(point_cloud, "QUERY_CHUNK", 97)
    assert len(voxels) > 10 * 97 and np.array_equal(point_cloud.without_statistical_outliers(voxels), whole)
