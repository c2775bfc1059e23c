"""Submaps: short, locally consistent stretches of the drive, matched against as one piece.

A submap is a run of consecutive key frames (processed scans) whose poses relative to its first
key frame (its *anchor*) come from the front end; those relative poses are trusted, and the pose
graph moves each submap as a rigid whole through its anchor. For matching, a submap is a grid of
its scans' end points in the anchor's frame (``T_anchor_from_vehicle`` applied to each key frame's
points), blurred by about a cell and stored as uint8 with its max pyramid
(:class:`~slam_engine.backend.correlative.MatchGrid`). Cells that none of its scans looked at hold
a neutral value (``loop_closing.unobserved_score``) instead of 0: an end point there is neither a
hit nor a miss, so a scan that sees more than the submap did is not held against its true pose.
What a scan looked across is the polygon from its position through its end points in bearing order.
Grids are built on demand and a few are kept (:class:`SubmapGrids`), so memory does not grow with
the drive.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numba as nb
import numpy as np

from slam_engine.backend.correlative import MatchGrid
from slam_engine.backend.polygon_fill import fill_polygons
from slam_engine.model.poses import compose, place_points, point_bounds, relative

# weights of the blur around each end point's cell (a Gaussian of about 0.8 cells): matches a cell
# off still score, but less; the cell itself has weight 1
BLUR_SIDE = 0.45  # the four cells beside it
BLUR_CORNER = 0.2  # the four cells diagonal to it


@dataclass(frozen=True)
class Submap:
    """Key frames ``first``..``last`` (inclusive); ``anchor = first``."""

    index: int
    first: int
    last: int

    @property
    def anchor(self) -> int:
        return self.first

    def nodes(self) -> range:
        return range(self.first, self.last + 1)


def split_into_submaps(path_length_m: np.ndarray, length_m: float, max_nodes: int,
                       breaks: np.ndarray | None = None) -> list[Submap]:
    """Consecutive submaps of about ``length_m`` of travel (and at most ``max_nodes`` key frames)
    over key frames whose cumulative travel is ``path_length_m`` (K,); a key frame where ``breaks``
    (K,) bool is set starts a new submap (its pose relative to the one before is not trusted)."""
    submaps: list[Submap] = []
    first = 0
    for k in range(1, len(path_length_m)):
        if path_length_m[k] - path_length_m[first] >= length_m or k - first + 1 > max_nodes \
                or (breaks is not None and breaks[k]):
            submaps.append(Submap(len(submaps), first, k - 1))
            first = k
    submaps.append(Submap(len(submaps), first, len(path_length_m) - 1))
    return submaps


def submap_scans(submap: Submap, poses: np.ndarray, points_v: list[np.ndarray]
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each key frame of the submap as (its position (2,), its end points (B, 2)), in the anchor frame
    [m], placed by ``poses``."""
    anchor = poses[submap.anchor]
    out = []
    for k in submap.nodes():
        T = relative(anchor, poses[k])
        out.append((T[:2].copy(), place_points(T, points_v[k])))
    return out


def observed_mask(scans: list[tuple[np.ndarray, np.ndarray]], lo_m: np.ndarray, shape: tuple[int, int],
                  resolution_m: float) -> np.ndarray:
    """(H, W) bool: cells that a scan of ``scans`` (position, end points; grid frame [m]) saw, i.e.
    lie inside the polygon from its position through its end points in bearing order (the free space
    it looked across, up to and including what it hit). Cell (0, 0)'s lower corner is at ``lo_m``.
    Rasterised by :func:`~slam_engine.backend.polygon_fill.fill_polygons`."""
    shift = 4  # sub-cell vertex precision: 1/16 cell
    rings = []
    for origin, pts in scans:
        if len(pts) < 2:
            continue
        bearing = np.arctan2(pts[:, 1] - origin[1], pts[:, 0] - origin[0])
        rings.append(np.vstack([origin[None, :], pts[np.argsort(bearing)]]))
    mask = np.zeros(shape, np.uint8)
    if rings:
        vertices = np.concatenate(rings)
        cells = np.round(((vertices - lo_m) / resolution_m - 0.5) * (1 << shift)).astype(np.int64)
        starts = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
        fill_polygons(mask, np.ascontiguousarray(cells[:, 0]), np.ascontiguousarray(cells[:, 1]), starts, shift)
    return mask.astype(bool)


def match_grid_from_points(points_m: np.ndarray, resolution_m: float, margin_m: float, n_levels: int = 9,
                           scans: list[tuple[np.ndarray, np.ndarray]] | None = None, unobserved: float = 0.0
                           ) -> MatchGrid:
    """A blurred hit grid of ``points_m`` (N, 2) [m] with ``margin_m`` of empty border. Each point
    marks the four cells around it with its bilinear weights (the largest weight a cell gets is kept),
    so a wall between two cell centres stays there when the grid is interpolated. With ``scans``
    (:func:`submap_scans`), cells none of them saw hold at least ``unobserved`` (in [0, 1]): a point
    there is neither a hit nor a miss (what the submap never looked at cannot contradict a scan)."""
    if margin_m < resolution_m:
        raise ValueError(f"match_grid_from_points: margin_m {margin_m} is less than a cell ({resolution_m} m)")
    lowest, highest = point_bounds(points_m)
    lo = lowest - margin_m
    hi = highest + margin_m
    shape = (int(np.ceil((hi[1] - lo[1]) / resolution_m)) + 2, int(np.ceil((hi[0] - lo[0]) / resolution_m)) + 2)
    values = _blurred_hits(np.ascontiguousarray(points_m, np.float64), float(lo[0]), float(lo[1]), float(resolution_m),
                           shape[0], shape[1], BLUR_SIDE, BLUR_CORNER)
    seen = None
    if scans is not None and unobserved > 0:
        seen = observed_mask(scans, lo, shape, resolution_m)
        values = np.where(seen, values, np.maximum(values, _to_uint8(np.float32(unobserved))))
    grid = MatchGrid.from_values(values, lo, resolution_m, n_levels)
    grid.bounds_m = np.concatenate([lowest, highest])
    grid.observed = seen
    return grid


def _to_uint8(weight: np.float32) -> np.uint8:
    """A weight in [0, 1] as a match-grid value (float32 arithmetic, rounded half to even)."""
    return np.uint8(np.rint(np.float32(255.0) * weight))


@nb.njit(cache=True, nogil=True)
def _blurred_hits(points_m, lo_x, lo_y, resolution_m, rows, cols, blur_side, blur_corner):
    """(rows, cols) uint8 values of :func:`match_grid_from_points` (before ``unobserved``): each point
    marks the four cells around it with its bilinear weights (float32; a cell keeps its largest),
    doubled and capped at 1, blurred by the largest of its own and its neighbours' weights times the
    blur's, and scaled to 0-255 (rounding is monotonic, so rounding before the maxima gives the same
    values). Only the cells the points touch are visited: O(points), whatever the grid's size."""
    hit = np.zeros((rows, cols), np.float32)
    n = points_m.shape[0]
    for k in range(n):
        u = (points_m[k, 0] - lo_x) / resolution_m - 0.5
        v = (points_m[k, 1] - lo_y) / resolution_m - 0.5
        i0 = np.int64(math.floor(u))
        j0 = np.int64(math.floor(v))
        fu = u - i0
        fv = v - j0
        hit[j0, i0] = max(hit[j0, i0], np.float32((1 - fu) * (1 - fv)))
        hit[j0, i0 + 1] = max(hit[j0, i0 + 1], np.float32(fu * (1 - fv)))
        hit[j0 + 1, i0] = max(hit[j0 + 1, i0], np.float32((1 - fu) * fv))
        hit[j0 + 1, i0 + 1] = max(hit[j0 + 1, i0 + 1], np.float32(fu * fv))
    out = np.zeros((rows, cols), np.uint8)
    side = np.float32(blur_side)
    corner = np.float32(blur_corner)
    for t in range(4 * n):  # each point's four cells again; a cell is blurred once (then marked -1)
        k = t >> 2
        i = np.int64(math.floor((points_m[k, 0] - lo_x) / resolution_m - 0.5)) + (t & 1)
        j = np.int64(math.floor((points_m[k, 1] - lo_y) / resolution_m - 0.5)) + ((t >> 1) & 1)
        raw = hit[j, i]
        if raw <= 0:
            continue
        hit[j, i] = -1.0
        weight = min(np.float32(1.0), np.float32(2.0) * raw)  # a point between cells still marks both fully
        for y in range(max(j - 1, 0), min(j + 2, rows)):
            for x in range(max(i - 1, 0), min(i + 2, cols)):
                if y == j and x == i:
                    blurred = weight
                elif y == j or x == i:
                    blurred = side * weight
                else:
                    blurred = corner * weight
                value = np.uint8(np.rint(np.float32(255.0) * blurred))
                if out[y, x] < value:
                    out[y, x] = value
    return out


class SubmapGrids:
    """Match grids of submaps, built when first asked for and kept for the ``keep`` most recently
    used, as long as they hold at most ``keep_bytes`` together (the newest is always kept; a grid
    with its pyramid is a few MB). ``poses`` are the front end's key-frame poses (only relative
    poses within a submap matter)."""

    def __init__(self, submaps: list[Submap], poses: np.ndarray, points_v: list[np.ndarray], resolution_m: float,
                 margin_m: float, keep: int = 8, keep_bytes: int = 16 * 1024**2, unobserved: float = 0.0):
        self.submaps = submaps
        self.poses = poses
        self.points_v = points_v
        self.resolution_m = resolution_m
        self.margin_m = margin_m
        self.keep = keep
        self.keep_bytes = keep_bytes
        self.unobserved = unobserved
        self._cache: OrderedDict[int, MatchGrid | None] = OrderedDict()

    def grid(self, index: int) -> MatchGrid | None:
        """The submap's match grid (None when it holds no end point)."""
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        scans = submap_scans(self.submaps[index], self.poses, self.points_v)
        pts = np.concatenate([p for _, p in scans]) if scans else np.zeros((0, 2))
        grid = (match_grid_from_points(pts, self.resolution_m, self.margin_m, scans=scans, unobserved=self.unobserved)
                if len(pts) else None)
        self._cache[index] = grid
        while len(self._cache) > 1 and (len(self._cache) > self.keep or self.cached_bytes() > self.keep_bytes):
            self._cache.popitem(last=False)
        return grid

    def cached_bytes(self) -> int:
        """Bytes of the grids kept (values and pyramids)."""
        return sum(g.values.nbytes + g.pyramid.nbytes + (0 if g.observed is None else g.observed.nbytes)
                   for g in self._cache.values() if g is not None)


def node_in_submap_frame(anchor_pose: np.ndarray, node_pose: np.ndarray) -> np.ndarray:
    """``T_anchor_from_node`` of two world poses."""
    return relative(anchor_pose, node_pose)


def world_from_submap(anchor_pose: np.ndarray, pose_in_submap: np.ndarray) -> np.ndarray:
    """A pose given in the submap (anchor) frame, in the world frame."""
    return compose(anchor_pose, pose_in_submap)
