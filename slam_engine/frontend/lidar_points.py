"""LiDAR ranges -> 2-D beam end points in the vehicle frame.

Each beam becomes a point through the full ``T_vehicle_from_lidar`` (4x4). A LiDAR whose scan
plane is tilted (roll or pitch in its extrinsic) is transformed as an Open3D point cloud; its
points below ``ground_z_m`` (ground hits) or above ``ceiling_z_m`` are dropped and the rest are
projected onto the plane. A level LiDAR (rotation about z only) takes a NumPy fast path and no
height filter (all its points lie at the mounting height).

Returns beyond the grid's ``max_range_m`` stay as free-space-only rays: they clear the cells they
cross up to ``max_range_m`` and never add a hit or take part in matching. Beams without a return
(``inf``, outside ``[range_min_m, range_max_m]``) clear up to ``no_return_clear_m`` (0 = not at
all; nothing for scanners whose ``range_max_m`` is below ``no_return_min_sensor_range_m``): many
scanners also report "no return" for dark or glass surfaces close by, and clearing far
along such beams erases real walls.

With ``no_return_bounded`` a beam without a return clears only what it is evidence for: up to
``no_return_stop_short_m`` short of the line joining the returns of the nearest returned beams on
either side of it in the same scan (:func:`bracketed_no_return_m`; stopping short keeps the wall
cells near that line, which the beam meets at a slant, from being cleared). A window or glass door
in a wall is bracketed by the wall's returns, so its beams stop at the wall instead of drawing rays
around the building; a scan without any return clears the full ``no_return_clear_m``. Only level
LiDARs are bounded so: a tilted LiDAR's no-return beams are mostly beams into the sky (the car's
LMS511 fans up over the street between the facades that bracket it) and already stop where they
leave the height band; bounding them would take the street ahead out of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_engine.model.drive_log import LidarModel
from slam_engine.model.poses import is_planar_4x4


@dataclass(frozen=True)
class ProjectedScan:
    """One scan in the vehicle frame: ``ends_v`` (K, 2) ray end points [m], ``is_hit`` (K,) False
    for free-space-only rays, ``free_from_m`` (K,) where each ray starts clearing cells [m]
    (:func:`free_space_start_m`), ``hits_v`` (H, 2) the returned end points (for matching),
    ``beams`` (K,) the index of each ray's beam in the scan (None when not known)."""

    ends_v: np.ndarray
    is_hit: np.ndarray
    free_from_m: np.ndarray
    beams: np.ndarray | None = None

    @property
    def hits_v(self) -> np.ndarray:
        return self.ends_v[self.is_hit]


class ScanProjector:
    """Projects the scans of one LiDAR. ``origin_v`` (2,) is the LiDAR's position in the vehicle
    frame [m], where every ray starts."""

    def __init__(self, lidar: LidarModel, max_range_m: float, ground_z_m: float, ceiling_z_m: float,
                 resolution_m: float, no_return_clear_m: float | None = None,
                 no_return_min_sensor_range_m: float = 0.0, no_return_bounded: bool = False,
                 no_return_stop_short_m: float = 0.5):
        self.lidar = lidar
        self.T = np.asarray(lidar.T_vehicle_from_lidar, dtype=np.float64)
        self.planar = is_planar_4x4(self.T)
        angles = lidar.beam_angles_rad
        self.dirs_lidar = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        self.dirs_v = self.dirs_lidar @ self.T[:2, :2].T
        self.origin_v = self.T[:2, 3].copy()
        self.max_range_m = float(max_range_m)
        self.clear_range_m = float(min(lidar.range_max_m, max_range_m))
        self.no_return_clear_m = self.clear_range_m if no_return_clear_m is None else \
            float(min(no_return_clear_m, self.clear_range_m))
        if lidar.range_max_m < no_return_min_sensor_range_m:
            self.no_return_clear_m = 0.0
        self.no_return_bounded = bool(no_return_bounded)
        self.no_return_stop_short_m = float(no_return_stop_short_m)
        self.ground_z_m = float(ground_z_m)
        self.ceiling_z_m = float(ceiling_z_m)
        self.free_from_m = free_space_start_m(lidar.num_beams, lidar.angle_increment_rad, resolution_m)

    def project(self, ranges_m: np.ndarray, beam_poses: np.ndarray | None = None,
                angle_offset_rad: float = 0.0) -> ProjectedScan:
        """(num_beams,) ranges [m] -> :class:`ProjectedScan`. ``beam_poses`` (num_beams, 3): where the
        vehicle was when each beam was measured, in its frame at the scan's reference time (de-skew,
        :func:`slam_engine.frontend.time_offset.sweep_poses`); each end point is moved by its beam's pose (the
        rays still start at ``origin_v``). ``angle_offset_rad``: this scan's beams point that much further
        counter-clockwise than the model's [rad] (:class:`~slam_engine.model.drive_log.ScanStream`)."""
        scan = self._project(ranges_m, *self._directions(angle_offset_rad))
        if beam_poses is None or scan.beams is None:
            return scan
        return _moved(scan, np.asarray(beam_poses, dtype=np.float64)[scan.beams])

    def _directions(self, angle_offset_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """The beams' unit directions in the LiDAR and the vehicle frame, (num_beams, 2) each, for a scan
        whose beams are turned by ``angle_offset_rad`` [rad] (0: the model's, computed once)."""
        if angle_offset_rad == 0.0:
            return self.dirs_lidar, self.dirs_v
        angles = self.lidar.beam_angles_rad + float(angle_offset_rad)
        dirs_lidar = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        return dirs_lidar, dirs_lidar @ self.T[:2, :2].T

    def _project(self, ranges_m: np.ndarray, dirs_lidar: np.ndarray, dirs_v: np.ndarray) -> ProjectedScan:
        r = np.asarray(ranges_m, dtype=np.float64)
        if r.shape != (self.lidar.num_beams,):
            raise ValueError(f"scan has {r.shape} ranges, the LiDAR model {self.lidar.name!r} "
                             f"has {self.lidar.num_beams} beams")
        returned = returned_beams(r, self.lidar)
        is_hit = returned & (r <= self.max_range_m)
        no_return_m = np.full(r.shape, self.no_return_clear_m)
        if self.no_return_bounded and self.planar and self.no_return_clear_m > 0 and not returned.all():
            bound = bracketed_no_return_m(r, returned, dirs_lidar) - self.no_return_stop_short_m
            no_return_m = np.minimum(no_return_m, np.maximum(bound, 0.0))
        length = np.where(is_hit, r, np.where(returned, self.clear_range_m, no_return_m))
        keep = length > 0
        if not keep.all():
            length, is_hit = length[keep], is_hit[keep]
        if self.planar:
            ends = self.origin_v + dirs_v[keep] * length[:, None]
            return ProjectedScan(ends_v=ends, is_hit=is_hit, free_from_m=self.free_from_m[keep],
                                 beams=np.flatnonzero(keep))
        return self._project_tilted(length, is_hit, keep, dirs_lidar)

    def _project_tilted(self, length: np.ndarray, is_hit: np.ndarray, beams: np.ndarray,
                        dirs_lidar: np.ndarray) -> ProjectedScan:
        import open3d as o3d

        pts_lidar = np.zeros((length.shape[0], 3))
        pts_lidar[:, :2] = dirs_lidar[beams] * length[:, None]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts_lidar))
        cloud.transform(self.T)
        pts_v = np.asarray(cloud.points)
        z = pts_v[:, 2]
        inside = (z >= self.ground_z_m) & (z <= self.ceiling_z_m)
        # hits outside the height band (ground, overhangs) are dropped; free rays are kept, shortened
        # to where they leave the band
        keep = np.where(is_hit, inside, True)
        ends = pts_v[:, :2].copy()
        free_tilted = ~is_hit & ~inside
        if free_tilted.any():
            dz = z[free_tilted] - self.T[2, 3]
            limit = np.where(dz < 0, self.ground_z_m, self.ceiling_z_m) - self.T[2, 3]
            frac = np.clip(np.divide(limit, dz, out=np.ones_like(dz), where=dz != 0), 0.0, 1.0)
            ends[free_tilted] = self.origin_v + (ends[free_tilted] - self.origin_v) * frac[:, None]
        return ProjectedScan(ends_v=ends[keep], is_hit=is_hit[keep], free_from_m=self.free_from_m[beams][keep],
                             beams=np.flatnonzero(beams)[keep])


def _moved(scan: ProjectedScan, poses: np.ndarray) -> ProjectedScan:
    """``scan`` with each end point moved by its (K, 3) pose: ``R(theta) p + (x, y)``."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x, y = scan.ends_v[:, 0], scan.ends_v[:, 1]
    ends = np.column_stack([poses[:, 0] + c * x - s * y, poses[:, 1] + s * x + c * y])
    return ProjectedScan(ends_v=ends, is_hit=scan.is_hit, free_from_m=scan.free_from_m, beams=scan.beams)


def returned_beams(ranges_m: np.ndarray, lidar: LidarModel) -> np.ndarray:
    """Which of ``ranges_m`` (any shape) [m] are returns: finite and within the LiDAR's range (``inf``,
    NaN and readings outside ``[range_min_m, range_max_m]`` mean no return)."""
    return np.isfinite(ranges_m) & (ranges_m >= lidar.range_min_m) & (ranges_m <= lidar.range_max_m)


def bracketed_no_return_m(ranges_m: np.ndarray, returned: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(B,) for each beam, the distance [m] along it to the line joining the end points of the nearest
    returned beams before and after it (``dirs`` (B, 2) unit beam directions in the scan plane,
    ``returned`` (B,) bool); the one bracketing return's range where only one side has a return
    (scan edges); ``inf`` where the scan has no return at all. Meaningful for the beams that did not
    return."""
    n = ranges_m.shape[0]
    index = np.arange(n)
    before = np.maximum.accumulate(np.where(returned, index, -1))
    after = np.minimum.accumulate(np.where(returned, index, n)[::-1])[::-1]
    has_before, has_after = before >= 0, after < n
    b, a = np.clip(before, 0, n - 1), np.clip(after, 0, n - 1)
    r = np.where(returned, ranges_m, 0.0)
    p_before = dirs[b] * r[b, None]
    p_after = dirs[a] * r[a, None]
    edge = p_after - p_before
    # beam t * d meets p_before + u * edge where t * cross(d, edge) = cross(p_before, edge)
    denominator = dirs[:, 0] * edge[:, 1] - dirs[:, 1] * edge[:, 0]
    numerator = p_before[:, 0] * edge[:, 1] - p_before[:, 1] * edge[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = numerator / denominator
    farther = np.maximum(r[b], r[a])
    both = np.where(np.isfinite(t) & (t > 0), np.minimum(t, farther), farther)
    return np.where(has_before & has_after, both, np.where(has_before, r[b], np.where(has_after, r[a], np.inf)))


def free_space_start_m(n_beams: int, angle_increment_rad: float, resolution_m: float) -> np.ndarray:
    """(n_beams,) distance [m] from which each beam clears free space. Near the LiDAR neighbouring
    beams are far less than a cell apart and would clear the same cells over and over: beam i, with
    ``v`` trailing zero bits in its index, starts at ``resolution / (|increment| * 2**v)``, so that
    at any distance the beams in use are at most half a cell apart (beam 0 starts at the LiDAR)."""
    index = np.arange(n_beams)
    trailing = np.zeros(n_beams, np.int64)
    for k in range(1, 32):
        trailing += (index > 0) & (index % (1 << k) == 0)
    start = resolution_m / (max(abs(angle_increment_rad), 1e-9) * 2.0 ** trailing)
    start[0] = 0.0
    return start
