"""A map that outlives its drive: what a later drive needs to localise in it, extend it or merge it.

Frames: every pose is ``[x_m, y_m, theta_rad]`` of the vehicle in the map frame (the first drive's);
every point is in the vehicle frame of its key frame [m]. Key frames are the scans the front end
processed; ``drive`` numbers the drives a map was built from (0 = the first, 1 = a drive that extended
it, ...). File format and version: :mod:`slam_engine.products.map_bundle`, ``docs/map-bundle.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from slam_engine.frontend.lidar_points import ProjectedScan


@dataclass
class StoredPlaces:
    """A map's place index as the bundle keeps it (:mod:`slam_engine.backend.place_index`): ``centres`` (P, 2)
    [m, map frame], ``bins`` (P, rings, sectors) bool (a bin holds an end point), the ``radius_m`` the bins
    cover and the ``spacing_m`` the places were laid out at."""

    centres: np.ndarray
    bins: np.ndarray
    radius_m: float
    spacing_m: float


@dataclass
class MapBundle:
    """Key frames at their optimised poses with the scans that drew the map, the pose graph's
    constraints and the per-scan trajectory of every drive.

    - ``poses`` (K, 3) map frame; ``t_s`` (K,) [s]; ``drive`` (K,) int; ``unverified`` (K,) bool: the
      motion into the key frame was not verified by a scan match (or the key frame starts a drive);
    - ``scan_offsets`` (K + 1,): key frame k's rays are rows ``scan_offsets[k]:scan_offsets[k + 1]`` of
      ``ends_v`` (N, 2) float32 [m, vehicle frame], ``is_hit`` (N,) bool (False: a ray that only clears
      free space) and ``free_from_m`` (N,) float32 (where each ray starts clearing cells);
    - ``origin_v`` (2,): the LiDAR's position in the vehicle frame [m], where every ray starts;
    - ``edges_ij`` (E, 2) int, ``edges_T_i_from_j`` (E, 3), ``edges_sigmas`` (E, 3) [m, m, rad],
      ``edges_robust`` (E,) bool: the pose graph (motions and accepted loop closures);
    - ``trajectory_t_s`` (S,), ``trajectory`` (S, 3), ``trajectory_drive`` (S,): every scan's pose;
    - ``resolution_m``: the grid's cell size; ``config``: the SlamConfig as JSON-ready settings;
      ``sensors``: the LiDAR set-up (model, beams, range) as JSON-ready settings;
    - ``places``: its place index, when made (a map that was built on or merged has none until it is made
      again: :func:`slam_engine.multisession.localization.map_places_of`).
    """

    poses: np.ndarray
    t_s: np.ndarray
    drive: np.ndarray
    unverified: np.ndarray
    scan_offsets: np.ndarray
    ends_v: np.ndarray
    is_hit: np.ndarray
    free_from_m: np.ndarray
    origin_v: np.ndarray
    edges_ij: np.ndarray
    edges_T_i_from_j: np.ndarray  # noqa: N815  (a frame name, as T_vehicle_from_lidar)
    edges_sigmas: np.ndarray
    edges_robust: np.ndarray
    trajectory_t_s: np.ndarray
    trajectory: np.ndarray
    trajectory_drive: np.ndarray
    resolution_m: float
    config: dict = field(default_factory=dict)
    sensors: dict = field(default_factory=dict)
    places: StoredPlaces | None = None

    def __len__(self) -> int:
        return int(len(self.poses))

    @property
    def drives(self) -> int:
        return int(self.drive.max()) + 1 if len(self.drive) else 0

    def scan(self, k: int) -> ProjectedScan:
        """Key frame k's rays as the map builder takes them."""
        rows = slice(int(self.scan_offsets[k]), int(self.scan_offsets[k + 1]))
        return ProjectedScan(self.ends_v[rows].astype(np.float64), self.is_hit[rows],
                             self.free_from_m[rows].astype(np.float64))

    def scans(self) -> list[ProjectedScan]:
        return [self.scan(k) for k in range(len(self))]

    def hits(self, k: int) -> np.ndarray:
        """(H, 2) key frame k's returned end points [m, vehicle frame] (what matching uses)."""
        rows = slice(int(self.scan_offsets[k]), int(self.scan_offsets[k + 1]))
        return self.ends_v[rows][self.is_hit[rows]].astype(np.float64)

    def all_hits(self) -> list[np.ndarray]:
        return [self.hits(k) for k in range(len(self))]

    @staticmethod
    def pack_scans(scans: Sequence[ProjectedScan]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(scan_offsets, ends_v, is_hit, free_from_m) of ``scans``, as a bundle stores them. ``scans`` is
        read twice, one scan at a time (a lazily projected sequence, as the filter keeps its key frames,
        is never held whole): once for the counts, once into the arrays."""
        counts = [len(scan.ends_v) for scan in scans]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        n = int(offsets[-1])
        ends_v, is_hit, free_from = np.empty((n, 2), np.float32), np.empty(n, bool), np.empty(n, np.float32)
        for k, scan in enumerate(scans):
            rows = slice(int(offsets[k]), int(offsets[k + 1]))
            ends_v[rows], is_hit[rows], free_from[rows] = scan.ends_v, scan.is_hit, scan.free_from_m
        return offsets, ends_v, is_hit, free_from
