"""Exhaustive correlative scan matching over a wide window (Olson 2009), made fast by
branch and bound over a precomputed max pyramid (Hess et al. 2016, Cartographer).

A :class:`MatchGrid` holds a map as uint8 values in [0, 255] (255 = surely occupied, 0 = free or
unknown) and its pyramid: ``levels[h][y, x]`` is the largest value in the ``2**h`` x ``2**h`` cells
whose lowest corner is ``(x, y)``. The score of a pose is the mean value under the scan's end points;
a node of the search tree at level ``h`` stands for ``2**h x 2**h`` translations at one heading, and its
score on ``levels[h]`` bounds the score of every translation below it, so whole blocks of the window are
discarded once a better leaf is known. The result is the best pose on the grid's lattice (cell size,
angular step from the scan's reach); :func:`refine_pose` then fits it continuously (sub-cell).

Frames: the grid lives in its own frame ("submap frame"); poses are ``[x_m, y_m, theta_rad]`` of the
scan's vehicle frame in that frame; points are (B, 2) [m] in the vehicle frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from slam_engine.model.poses import wrap_angle

MAX_VALUE = 255
NO_ORIGINS = np.zeros((0, 0, 0), np.uint8)  # branch_and_bound's origins: every translation


def max_pyramid(values: np.ndarray, n_levels: int) -> np.ndarray:
    """(n_levels, H, W) uint8: level h holds the maximum of ``values`` over the ``2**h`` square block
    starting at each cell (cells beyond the edge count as 0)."""
    h, w = values.shape
    out = np.zeros((n_levels, h, w), np.uint8)
    if n_levels == 0:  # a grid only refined against (refine_pose) needs none
        return out
    out[0] = values
    for level in range(1, n_levels):
        half = 1 << (level - 1)
        prev = out[level - 1]
        cur = out[level]
        cur[:] = prev
        if half < w:
            np.maximum(cur[:, : w - half], prev[:, half:], out=cur[:, : w - half])
        if half < h:  # in place: row y reads row y + half, not yet changed
            np.maximum(cur[: h - half, :], cur[half:, :], out=cur[: h - half, :])
    return out


def mask_at(mask: np.ndarray, origin_m: np.ndarray, resolution_m: float, xy_m: np.ndarray) -> np.ndarray:
    """(N,) bool: ``mask`` (H, W, row = y; cell (0, 0)'s lower corner at ``origin_m``, cells of
    ``resolution_m``) at each point ``xy_m`` (N, 2) [m]; False off the mask."""
    ij = np.floor((np.asarray(xy_m, np.float64) - origin_m) / resolution_m).astype(np.int64)
    h, w = mask.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out = np.zeros(len(ij), bool)
    out[inside] = mask[ij[inside, 1], ij[inside, 0]]
    return out


@dataclass
class MatchGrid:
    """A map to match against: ``values`` (H, W) uint8 (row = y), cell (0, 0)'s lower corner at
    ``origin_m`` in the grid's frame, cells of ``resolution_m``; ``pyramid`` from :func:`max_pyramid`."""

    values: np.ndarray
    origin_m: np.ndarray
    resolution_m: float
    pyramid: np.ndarray
    bounds_m: np.ndarray | None = None  # [x_min, y_min, x_max, y_max] of what the map holds [m]
    observed: np.ndarray | None = None  # (H, W) bool like ``values``: cells a scan of the map saw

    def observed_at(self, xy_m: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each point ``xy_m`` (N, 2) [m, grid frame] lies in a cell the map saw
        (everywhere on the grid when ``observed`` is None; nowhere off it)."""
        mask = np.ones(self.values.shape, bool) if self.observed is None else self.observed
        return mask_at(mask, self.origin_m, self.resolution_m, xy_m)

    @classmethod
    def from_values(cls, values: np.ndarray, origin_m: np.ndarray, resolution_m: float, n_levels: int = 7
                    ) -> MatchGrid:
        values = np.ascontiguousarray(values, np.uint8)
        return cls(values, np.asarray(origin_m, np.float64), float(resolution_m), max_pyramid(values, n_levels))

    @property
    def n_levels(self) -> int:
        return int(self.pyramid.shape[0])

    def centre_and_reach(self) -> tuple[np.ndarray, float]:
        """The centre pose of what the map holds (heading 0) and the half width that covers all of it
        [m]: the window of a search over the whole map. Needs ``bounds_m``."""
        if self.bounds_m is None:
            raise ValueError("centre_and_reach: the grid has no bounds_m")
        lo, hi = self.bounds_m[:2], self.bounds_m[2:]
        return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0]), float(np.max(hi - lo)) / 2 + 1.0


@dataclass(frozen=True)
class CorrelativeMatch:
    """Best pose found (submap frame), its score (mean value in [0, 1]) and the best score found
    farther than the ambiguity distance from it (0 when none came close: a unique match), with that
    runner-up's pose (None when there is none)."""

    pose: np.ndarray
    score: float
    runner_up_score: float  # NaN: not searched for (see search())
    runner_up_pose: np.ndarray | None = None
    line_direction: np.ndarray | None = None  # (2,) unit, submap frame: ambiguous only along this line


@nb.njit(cache=True, nogil=True)
def _rotated_cells(points_v, x0, y0, theta0, angle_step, n_angles_half, origin_x, origin_y, inv_res):
    """(A, B, 2) int32 cells of the points rotated by theta0 + a * step and placed at (x0, y0)."""
    n_angles = 2 * n_angles_half + 1
    n = points_v.shape[0]
    out = np.empty((n_angles, n, 2), np.int32)
    for a in range(n_angles):
        th = theta0 + (a - n_angles_half) * angle_step
        c = math.cos(th)
        s = math.sin(th)
        for i in range(n):
            px = points_v[i, 0]
            py = points_v[i, 1]
            out[a, i, 0] = int(math.floor((x0 + c * px - s * py - origin_x) * inv_res))
            out[a, i, 1] = int(math.floor((y0 + s * px + c * py - origin_y) * inv_res))
    return out


@nb.njit(cache=True, nogil=True, inline="always")
def _score(pyramid, level, cells, a, dx, dy):
    """Sum over the points of heading a, shifted by (dx, dy), of their blocks' maxima on ``level``. A
    block that starts left of (or below) the grid and reaches into it is bounded by the block at the
    edge, which covers the part of it on the grid: an upper bound still, without padding the grid."""
    h = pyramid.shape[1]
    w = pyramid.shape[2]
    size = 1 << level
    total = 0
    for i in range(cells.shape[1]):
        x = cells[a, i, 0] + dx
        y = cells[a, i, 1] + dy
        if x < 0:
            if x + size <= 0:
                continue
            x = 0
        if y < 0:
            if y + size <= 0:
                continue
            y = 0
        if x < w and y < h:
            total += pyramid[level, y, x]
    return total


@nb.njit(cache=True, nogil=True, inline="always")
def _may_hold_origin(origins, level, x, y):
    """Whether the node's block of translations (``2**level`` a side from (x, y), in the origins'
    cells) puts the scan's origin on any allowed cell (``origins``: a max pyramid of the allowed cells;
    with no levels, everywhere)."""
    if origins.shape[0] == 0:
        return True
    size = 1 << level
    if x < 0:
        if x + size <= 0:
            return False
        x = 0
    if y < 0:
        if y + size <= 0:
            return False
        y = 0
    return x < origins.shape[2] and y < origins.shape[1] and origins[level, y, x] > 0


@nb.njit(cache=True, nogil=True, inline="always")
def _inside_exclusion(a, dx, dy, size, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy):
    """Whether every translation of the node (a, [dx, dx+size) x [dy, dy+size)) lies within the
    exclusion zone around (ex_a, ex_x, ex_y): a box of half width ``ex_cells``, or where the unit
    direction (ex_ux, ex_uy) is not zero, the strip of that half width along it (a line of poses)."""
    if ex_angles < 0 or abs(a - ex_a) > ex_angles:
        return False
    if ex_ux == 0.0 and ex_uy == 0.0:
        return (dx >= ex_x - ex_cells and dx + size - 1 <= ex_x + ex_cells
                and dy >= ex_y - ex_cells and dy + size - 1 <= ex_y + ex_cells)
    # the strip is convex: the node lies in it when its four corners do
    for cx in (dx - ex_x, dx + size - 1 - ex_x):
        for cy in (dy - ex_y, dy + size - 1 - ex_y):
            if abs(ex_ux * cy - ex_uy * cx) > ex_cells:
                return False
    return True


@nb.njit(cache=True, nogil=True, parallel=True)
def branch_and_bound(pyramid, cells, window_cells, min_total, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy,
                     n_shards, origins, origin_x, origin_y, first_only=False):
    """Best (a, dx, dy, total) over headings a and integer translations |dx|, |dy| <= window_cells,
    whose total exceeds ``min_total``; (-1, 0, 0, min_total) when none does. Nodes entirely inside the
    exclusion zone (``ex_angles`` >= 0; a box, or a strip along the unit direction ``(ex_ux, ex_uy)``)
    are skipped: a second search with it finds the best match that is *not* the first one. Only
    translations that put the scan's origin (at cell (origin_x, origin_y) untranslated) on a cell that
    ``origins`` allows are searched (a max pyramid like ``pyramid``'s, on the same cells, at least as
    many levels; an empty (0, 0, 0) array: every translation). ``first_only``: every shard stops as
    soon as one of them reaches a leaf that exceeds ``min_total``: whether there is one is the same
    for any number of shards, but with more than one which leaf is returned depends on their timing.

    The search is depth first from the best top-level node, the best child first; of equally good
    leaves, the first one reached wins. The top-level nodes are dealt out to ``n_shards`` shards,
    searched in parallel (:func:`_descend`); the result is the same for any number of shards."""
    top = pyramid.shape[0] - 1
    while top > 0 and (1 << top) > 2 * window_cells + 1:
        top -= 1
    size_top = 1 << top
    n_angles = cells.shape[0]
    per_axis = (2 * window_cells) // size_top + 1
    cap = n_angles * per_axis * per_axis
    st_a = np.empty(cap, np.int64)
    st_x = np.empty(cap, np.int64)
    st_y = np.empty(cap, np.int64)
    st_s = np.empty(cap, np.int64)
    # the top-level nodes: every heading, the window tiled by top-level blocks; searched best first
    m = 0
    for a in range(n_angles):
        for ix in range(per_axis):
            for iy in range(per_axis):
                dx = -window_cells + ix * size_top
                dy = -window_cells + iy * size_top
                if _inside_exclusion(a, dx, dy, size_top, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy):
                    continue
                if not _may_hold_origin(origins, top, origin_x + dx, origin_y + dy):
                    continue
                st_a[m] = a
                st_x[m] = dx
                st_y[m] = dy
                st_s[m] = _score(pyramid, top, cells, a, dx, dy)
                m += 1
    order = np.argsort(st_s[:m])
    top_a = st_a[:m][order]
    top_x = st_x[:m][order]
    top_y = st_y[:m][order]
    top_s = st_s[:m][order]
    shard_best = np.full(n_shards, min_total, np.int64)
    found = np.empty((n_shards, 5), np.int64)
    for shard in nb.prange(n_shards):
        _descend(pyramid, cells, window_cells, min_total, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy,
                 top, top_a, top_x, top_y, top_s, shard, n_shards, shard_best, found, origins, origin_x, origin_y,
                 first_only)
    # the best total; of equal ones, the one under the top-level node searched first
    best = 0
    for q in range(1, n_shards):
        if found[q, 3] > found[best, 3] or (found[q, 3] == found[best, 3] and found[q, 4] > found[best, 4]):
            best = q
    if found[best, 0] < 0:
        return -1, 0, 0, min_total
    return found[best, 0], found[best, 1], found[best, 2], found[best, 3]


@nb.njit(cache=True, nogil=True)
def _descend(pyramid, cells, window_cells, min_total, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy,
             top, top_a, top_x, top_y, top_s, shard, n_shards, shard_best, found, origins, origin_x, origin_y,
             first_only):
    """:func:`branch_and_bound` under the top-level nodes ``shard``, ``shard + n_shards``, ... counted
    from the best (the arrays ``top_*`` are sorted by score, ascending). Writes ``found[shard]`` =
    (a, dx, dy, total, position of its top-level node) of the first best leaf, (-1, 0, 0, min_total,
    -1) when none beats ``min_total``. A node is cut when it cannot beat this shard's best, or falls
    short of another shard's (``shard_best``, read while they run): a tie with another shard's best
    is still searched, so the result does not depend on how fast the shards run."""
    cap = 4 * (top + 2) + 1
    st_a = np.empty(cap, np.int64)
    st_x = np.empty(cap, np.int64)
    st_y = np.empty(cap, np.int64)
    st_h = np.empty(cap, np.int64)
    st_s = np.empty(cap, np.int64)
    best_total = min_total
    best_a, best_x, best_y, best_position = -1, 0, 0, -1
    ca = np.empty(4, np.int64)
    cx = np.empty(4, np.int64)
    cy = np.empty(4, np.int64)
    cs = np.empty(4, np.int64)
    stop = False
    for position in range(top_a.shape[0] - 1 - shard, -1, -n_shards):
        if stop:
            break
        st_a[0], st_x[0], st_y[0], st_h[0], st_s[0] = (top_a[position], top_x[position], top_y[position], top,
                                                       top_s[position])
        m = 1
        while m > 0:
            m -= 1
            s = st_s[m]
            if s <= best_total:
                continue
            others = min_total
            for q in range(n_shards):
                if q != shard and shard_best[q] > others:
                    others = shard_best[q]
            if first_only and others > min_total:  # another shard found one
                stop = True
                break
            if s < others:
                continue
            h = st_h[m]
            a, dx, dy = st_a[m], st_x[m], st_y[m]
            if h == 0:
                best_total, best_a, best_x, best_y, best_position = s, a, dx, dy, position
                shard_best[shard] = s
                if first_only:
                    stop = True
                    break
                continue
            half = 1 << (h - 1)
            k = 0
            for i in range(2):
                for j in range(2):
                    x = dx + i * half
                    y = dy + j * half
                    if x > window_cells or y > window_cells:
                        continue
                    if _inside_exclusion(a, x, y, half, ex_a, ex_x, ex_y, ex_angles, ex_cells, ex_ux, ex_uy):
                        continue
                    if not _may_hold_origin(origins, h - 1, origin_x + x, origin_y + y):
                        continue
                    sc = _score(pyramid, h - 1, cells, a, x, y)
                    if sc <= best_total or sc < others:
                        continue
                    ca[k], cx[k], cy[k], cs[k] = a, x, y, sc
                    k += 1
            # push the k children worst first, so that the best is expanded next
            for _ in range(k):
                lo = 0
                for q in range(1, k):
                    if cs[q] < cs[lo]:
                        lo = q
                st_a[m], st_x[m], st_y[m], st_h[m], st_s[m] = ca[lo], cx[lo], cy[lo], h - 1, cs[lo]
                m += 1
                cs[lo] = np.iinfo(np.int64).max
    found[shard, 0] = best_a
    found[shard, 1] = best_x
    found[shard, 2] = best_y
    found[shard, 3] = best_total
    found[shard, 4] = best_position


def angular_step_rad(points_v: np.ndarray, resolution_m: float, reach_cap_m: float = 10.0) -> float:
    """Heading step that moves the farthest point (capped at ``reach_cap_m``) by about one cell."""
    reach = float(np.max(np.hypot(points_v[:, 0], points_v[:, 1]))) if len(points_v) else 1.0
    reach = min(max(reach, 3.0 * resolution_m), reach_cap_m)
    return float(math.acos(max(-1.0, 1.0 - resolution_m**2 / (2.0 * reach**2))))


@dataclass(frozen=True)
class _Lattice:
    """The poses a search tries: translations in whole cells of ``res`` [m] from (``x0``, ``y0``) out to
    ``window_cells``, headings in whole ``step`` [rad] from ``th0`` out to ``n_half`` steps; ``cells``: the
    points rotated to each heading (:func:`_rotated_cells`); ``origins`` and the initial pose's cell on it
    (``origin_x``, ``origin_y``), as :func:`branch_and_bound` takes them."""

    res: float
    step: float
    n_half: int
    window_cells: int
    x0: float
    y0: float
    th0: float
    cells: np.ndarray
    origins: np.ndarray
    origin_x: int
    origin_y: int

    @classmethod
    def of(cls, grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float, window_rad: float,
           origins: np.ndarray | None) -> _Lattice:
        res, step, n_half, window_cells, x0, y0, th0 = _lattice_frame(grid, points_v, initial_pose, window_m,
                                                                      window_rad)
        cells = _rotated_cells(points_v, x0, y0, th0, step, n_half, float(grid.origin_m[0]), float(grid.origin_m[1]),
                               1.0 / res)
        if origins is None:
            origins, origin_x, origin_y = NO_ORIGINS, 0, 0
        else:
            if origins.shape[1:] != grid.values.shape or origins.shape[0] < grid.n_levels:
                raise ValueError("search: origins must be a max pyramid on the grid's cells with its levels")
            origin_x = int(math.floor((x0 - float(grid.origin_m[0])) / res))
            origin_y = int(math.floor((y0 - float(grid.origin_m[1])) / res))
        return cls(res, step, n_half, window_cells, x0, y0, th0, cells, origins, origin_x, origin_y)


def _lattice_frame(grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float,
                   window_rad: float) -> tuple[float, float, int, int, float, float, float]:
    """(res, step, n_half, window_cells, x0, y0, th0) of the lattice a search of ``points_v`` within ``window_m``
    / ``window_rad`` of ``initial_pose`` tries (:class:`_Lattice`), without the points rotated to it."""
    res = grid.resolution_m
    step = angular_step_rad(points_v, res)
    x0, y0, th0 = (float(v) for v in initial_pose)
    return (res, step, max(0, int(math.ceil(window_rad / step))), max(0, int(math.ceil(window_m / res))), x0, y0,
            th0)


def _exclusion_centre(best_pose: np.ndarray, res: float, step: float, n_half: int, x0: float, y0: float,
                      th0: float) -> tuple[int, int, int]:
    """(heading index, dx, dy) of ``best_pose`` on a search's lattice: the centre of the runner-up search's
    ambiguity box."""
    return (int(round(float(wrap_angle(float(best_pose[2]) - th0)) / step)) + n_half,
            int(round((float(best_pose[0]) - x0) / res)), int(round((float(best_pose[1]) - y0) / res)))


def search(grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float, window_rad: float,
           min_score: float, ambiguity_m: float = 0.0, ambiguity_rad: float = 0.0,
           runner_up_share: float = 0.0, line_half_width_m: float = 0.0, line_half_width_rad: float = 0.0,
           runner_up_min_score: float | None = None, threads: int = 1, runner_up_from: float = 0.0,
           origins: np.ndarray | None = None, any_runner_up: bool = False) -> CorrelativeMatch | None:
    """Best pose of ``points_v`` within ``window_m`` / ``window_rad`` of ``initial_pose`` scoring
    above ``min_score``, or None. With ``ambiguity_m`` > 0 a second search reports the best score
    of a pose more than ``ambiguity_m`` / ``ambiguity_rad`` from the best one (at least
    ``runner_up_share`` of the best score and ``runner_up_min_score`` (default ``min_score``) to count;
    else 0), and its pose. A ``min_score`` above ``runner_up_min_score`` only prunes: the best pose,
    when it scores above it, and the runner-up are those a lower ``min_score`` finds.

    With ``line_half_width_m`` > 0, an ambiguous match whose runner-up has the best's heading
    (within ``line_half_width_rad``) is tested for a *line* of equally good poses, as a corridor
    gives: a third search over every pose farther than ``line_half_width_m`` from the line through
    the two, or turned more than ``ambiguity_rad`` from the best. When nothing there reaches the
    runner-up share, the match is ambiguous only along that line, and ``line_direction`` holds the
    line's unit direction (submap frame): the heading is still found.

    The runner-up is searched for only when the best scores at least ``runner_up_from`` (a caller that
    refuses a weaker match anyway saves the second search, which takes as long as the first); below it,
    ``runner_up_score`` is NaN. ``any_runner_up``: the runner-up search stops at the first pose that
    reaches the share, whose score and pose are then the runner-up's (any such pose's, not the best,
    and with threads not always the same one: for a caller that only asks whether the match is
    ambiguous, which does not depend on it; when it is, much faster). No line test then.

    ``origins``: where the scan's origin (the vehicle) may be, as a max pyramid (:func:`max_pyramid`) of
    the allowed cells of ``grid`` (at least as many levels as its own); the search skips every other
    translation (a drive is where its map saw free space). None: anywhere.

    Each search runs in ``threads`` threads (the result does not depend on it)."""
    points_v = np.ascontiguousarray(points_v, np.float64)
    n = len(points_v)
    if n == 0:
        return None
    lattice = _Lattice.of(grid, points_v, initial_pose, window_m, window_rad, origins)
    res, step, n_half, window_cells, cells = (lattice.res, lattice.step, lattice.n_half, lattice.window_cells,
                                              lattice.cells)
    x0, y0, th0 = lattice.x0, lattice.y0, lattice.th0
    origins, origin_x, origin_y = lattice.origins, lattice.origin_x, lattice.origin_y
    min_total = int(min_score * MAX_VALUE * n)
    shards = max(1, int(threads))
    a, dx, dy, total = branch_and_bound(grid.pyramid, cells, window_cells, min_total, 0, 0, 0, -1, 0, 0.0, 0.0, shards,
                                        origins, origin_x, origin_y)
    if a < 0:
        return None
    pose = np.array([x0 + dx * res, y0 + dy * res, th0 + (a - n_half) * step])
    score = total / (MAX_VALUE * n)
    if ambiguity_m <= 0:
        return CorrelativeMatch(pose=pose, score=float(score), runner_up_score=0.0)
    if score < runner_up_from:
        return CorrelativeMatch(pose=pose, score=float(score), runner_up_score=math.nan)
    runner_up_total = min_total if runner_up_min_score is None else int(runner_up_min_score * MAX_VALUE * n)
    floor = int(max(runner_up_total, runner_up_share * total))
    ex_cells = int(math.ceil(ambiguity_m / res))
    ex_angles = int(math.ceil(ambiguity_rad / step))
    a2, dx2, dy2, total2 = branch_and_bound(grid.pyramid, cells, window_cells, floor, a, dx, dy, ex_angles,
                                            ex_cells, 0.0, 0.0, shards, origins, origin_x, origin_y, any_runner_up)
    if a2 < 0:
        return CorrelativeMatch(pose=pose, score=float(score), runner_up_score=0.0)
    runner_up_pose = np.array([x0 + dx2 * res, y0 + dy2 * res, th0 + (a2 - n_half) * step])
    line = None
    line_angles = int(math.floor(line_half_width_rad / step))
    if line_half_width_m > 0 and not any_runner_up and abs(a2 - a) <= line_angles and (dx2, dy2) != (dx, dy):
        u = np.array([dx2 - dx, dy2 - dy], np.float64)
        u /= np.hypot(u[0], u[1])
        a3, _, _, _ = branch_and_bound(grid.pyramid, cells, window_cells, floor, a, dx, dy, ex_angles,
                                       int(math.ceil(line_half_width_m / res)), float(u[0]), float(u[1]), shards,
                                       origins, origin_x, origin_y)
        if a3 < 0:
            line = u
    return CorrelativeMatch(pose=pose, score=float(score), runner_up_score=float(total2 / (MAX_VALUE * n)),
                            runner_up_pose=runner_up_pose, line_direction=line)


def lattice_pose(points_v: np.ndarray, resolution_m: float, initial_pose: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``pose`` moved to the nearest pose that :func:`search` from ``initial_pose`` tries on a grid of
    ``resolution_m`` with ``points_v`` (its translations: whole cells from the initial pose; its headings:
    whole angular steps from it). A search in a small window around that pose scores every pose as the
    search over a wide window around ``initial_pose`` would."""
    step = angular_step_rad(np.ascontiguousarray(points_v, np.float64), resolution_m)
    x0, y0, th0 = (float(v) for v in initial_pose)
    return np.array([x0 + round((float(pose[0]) - x0) / resolution_m) * resolution_m,
                     y0 + round((float(pose[1]) - y0) / resolution_m) * resolution_m,
                     th0 + round(float(wrap_angle(float(pose[2]) - th0)) / step) * step])


def runner_up_score(grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float,
                    window_rad: float, best_pose: np.ndarray, min_score: float, ambiguity_m: float,
                    ambiguity_rad: float, threads: int = 1, origins: np.ndarray | None = None) -> float:
    """The runner-up search of :func:`search` (``any_runner_up``) alone: the score of a pose of
    ``points_v`` within ``window_m`` / ``window_rad`` of ``initial_pose``, farther than ``ambiguity_m`` /
    ``ambiguity_rad`` from ``best_pose`` (on this search's lattice: :func:`lattice_pose`), that scores at
    least ``min_score`` (the first one found, not the best), or 0 when none does."""
    points_v = np.ascontiguousarray(points_v, np.float64)
    n = len(points_v)
    if n == 0:
        return 0.0
    lat = _Lattice.of(grid, points_v, initial_pose, window_m, window_rad, origins)
    ex_a, ex_x, ex_y = _exclusion_centre(best_pose, lat.res, lat.step, lat.n_half, lat.x0, lat.y0, lat.th0)
    a2, _, _, total = branch_and_bound(grid.pyramid, lat.cells, lat.window_cells, int(min_score * MAX_VALUE * n), ex_a,
                                       ex_x, ex_y, int(math.ceil(ambiguity_rad / lat.step)),
                                       int(math.ceil(ambiguity_m / lat.res)), 0.0, 0.0, max(1, int(threads)),
                                       lat.origins, lat.origin_x, lat.origin_y, True)
    return 0.0 if a2 < 0 else float(total / (MAX_VALUE * n))


def runner_up_among(grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float,
                    window_rad: float, best_pose: np.ndarray, min_score: float, ambiguity_m: float,
                    ambiguity_rad: float, matches: list[CorrelativeMatch]) -> float | None:
    """What :func:`runner_up_score` (same arguments) would find, read from poses already scored instead:
    the score of the first of ``matches`` (poses of ``points_v`` on that search's lattice, e.g. the best of
    small windows searched around it, with their scores) that its search would try and count (on the
    lattice and within the window, outside the ambiguity box around ``best_pose``, above ``min_score``);
    None when none of them is one. Either way the question it answers (is the best ambiguous?) gets the
    same answer; only a None needs the search itself."""
    points_v = np.ascontiguousarray(points_v, np.float64)
    n = len(points_v)
    if n == 0 or not matches:
        return None
    res, step, n_half, window_cells, x0, y0, th0 = _lattice_frame(grid, points_v, initial_pose, window_m, window_rad)
    ex_a, ex_x, ex_y = _exclusion_centre(best_pose, res, step, n_half, x0, y0, th0)
    ex_angles, ex_cells = int(math.ceil(ambiguity_rad / step)), int(math.ceil(ambiguity_m / res))
    floor_total = int(min_score * MAX_VALUE * n)
    for match in matches:
        x, y, theta = (float(v) for v in match.pose)
        a = int(round((theta - th0) / step)) + n_half  # unwrapped: beyond +-n_half the search tries no such heading
        dx, dy = int(round((x - x0) / res)), int(round((y - y0) / res))
        on_lattice = abs(th0 + (a - n_half) * step - theta) < 1e-6 * step and abs(x0 + dx * res - x) < 1e-6 * res \
            and abs(y0 + dy * res - y) < 1e-6 * res
        inside = 0 <= a <= 2 * n_half and abs(dx) <= window_cells and abs(dy) <= window_cells
        excluded = abs(a - ex_a) <= ex_angles and abs(dx - ex_x) <= ex_cells and abs(dy - ex_y) <= ex_cells
        if on_lattice and inside and not excluded and int(round(match.score * MAX_VALUE * n)) > floor_total:
            return match.score
    return None


@nb.njit(cache=True, nogil=True)
def _dense_residuals(values, origin_x, origin_y, inv_res, points_v, x, y, theta, H, g):
    """Sum of (1 - v)^2 at the points (v bilinear in [0, 1]) and the Gauss-Newton system."""
    c = math.cos(theta)
    s = math.sin(theta)
    for a in range(3):
        g[a] = 0.0
        for b in range(3):
            H[a, b] = 0.0
    rows = values.shape[0]
    cols = values.shape[1]
    e = 0.0
    for i in range(points_v.shape[0]):
        px = points_v[i, 0]
        py = points_v[i, 1]
        wx = x + c * px - s * py
        wy = y + s * px + c * py
        u = (wx - origin_x) * inv_res - 0.5
        v = (wy - origin_y) * inv_res - 0.5
        i0 = int(math.floor(u))
        j0 = int(math.floor(v))
        fu = u - i0
        fv = v - j0
        if i0 < 0 or j0 < 0 or i0 + 1 >= cols or j0 + 1 >= rows:
            e += 1.0
            continue
        v00 = values[j0, i0] / 255.0
        v10 = values[j0, i0 + 1] / 255.0
        v01 = values[j0 + 1, i0] / 255.0
        v11 = values[j0 + 1, i0 + 1] / 255.0
        m = (1.0 - fv) * ((1.0 - fu) * v00 + fu * v10) + fv * ((1.0 - fu) * v01 + fu * v11)
        mx = ((1.0 - fv) * (v10 - v00) + fv * (v11 - v01)) * inv_res
        my = ((1.0 - fu) * (v01 - v00) + fu * (v11 - v10)) * inv_res
        r = 1.0 - m
        jt = mx * (-s * px - c * py) + my * (c * px - s * py)
        H[0, 0] += mx * mx
        H[0, 1] += mx * my
        H[0, 2] += mx * jt
        H[1, 1] += my * my
        H[1, 2] += my * jt
        H[2, 2] += jt * jt
        g[0] += mx * r
        g[1] += my * r
        g[2] += jt * r
        e += r * r
    H[1, 0] = H[0, 1]
    H[2, 0] = H[0, 2]
    H[2, 1] = H[1, 2]
    return e


@nb.njit(cache=True, nogil=True)
def _refine(values, origin_x, origin_y, inv_res, points_v, pose, iterations):
    H = np.zeros((3, 3))
    g = np.zeros(3)
    H2 = np.zeros((3, 3))
    g2 = np.zeros(3)
    e = _dense_residuals(values, origin_x, origin_y, inv_res, points_v, pose[0], pose[1], pose[2], H, g)
    lam = 1e-3
    A = np.zeros((3, 3))
    cand = np.zeros(3)
    for _ in range(iterations):
        for a in range(3):
            for b in range(3):
                A[a, b] = H[a, b]
            A[a, a] += lam * (H[a, a] + 1e-9) + 1e-9
        step = np.linalg.solve(A, g)
        for a in range(3):
            cand[a] = pose[a] + step[a]
        e2 = _dense_residuals(values, origin_x, origin_y, inv_res, points_v, cand[0], cand[1], cand[2], H2, g2)
        if e2 < e:
            for a in range(3):
                pose[a] = cand[a]
                g[a] = g2[a]
                for b in range(3):
                    H[a, b] = H2[a, b]
            e = e2
            lam *= 0.3
            if abs(step[0]) + abs(step[1]) < 1e-4 and abs(step[2]) < 1e-5:
                break
        else:
            lam *= 8.0
            if lam > 1e4:
                break
    return e


# a refined pose farther than this from its start keeps the start [cells, rad]
REFINE_MAX_SHIFT_CELLS = 1.5
REFINE_MAX_TURN_RAD = 0.02


def fit_pose(grid: MatchGrid, points_v: np.ndarray, pose: np.ndarray, iterations: int = 30) -> np.ndarray:
    """The local optimum of ``points_v`` (N, 2) [m, vehicle frame] on ``grid`` from ``pose`` (Levenberg-
    Marquardt on the bilinear grid values, as :func:`refine_pose`, but unbounded): a tracker's step
    when its prediction is within the grid's blur of the truth. The caller checks how far it moved."""
    fitted = np.asarray(pose, np.float64).copy()
    _refine(grid.values, float(grid.origin_m[0]), float(grid.origin_m[1]), 1.0 / grid.resolution_m,
            np.ascontiguousarray(points_v, np.float64), fitted, iterations)
    return fitted


def refine_pose(grid: MatchGrid, points_v: np.ndarray, pose: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Sub-cell fit of ``pose`` (Levenberg-Marquardt on the bilinear grid values), kept within one
    cell and one angular step of the start (a lattice match is already that close)."""
    start = np.asarray(pose, np.float64)
    fitted = start.copy()
    _refine(grid.values, float(grid.origin_m[0]), float(grid.origin_m[1]), 1.0 / grid.resolution_m,
            np.ascontiguousarray(points_v, np.float64), fitted, iterations)
    if (np.hypot(*(fitted[:2] - start[:2])) > REFINE_MAX_SHIFT_CELLS * grid.resolution_m
            or abs(fitted[2] - start[2]) > REFINE_MAX_TURN_RAD):
        return start
    return fitted


@nb.njit(cache=True, nogil=True, parallel=True)
def _refine_many(values, origin_x, origin_y, inv_res, points_v, starts, first, step, nodes, poses, iterations):
    """:func:`_refine` of ``poses[k]`` (in place) for each ``k`` in ``nodes``, with the end points
    ``points_v[starts[k] + first:starts[k + 1]:step]``; key frames in parallel threads (each fit
    reads only the grid and writes only its own pose: the same poses as one by one)."""
    for n in nb.prange(nodes.shape[0]):
        k = nodes[n]
        _refine(values, origin_x, origin_y, inv_res, points_v[starts[k] + first:starts[k + 1]:step], poses[k],
                iterations)


def refine_poses(grid: MatchGrid, points_v: np.ndarray, starts: np.ndarray, poses: np.ndarray, nodes: np.ndarray,
                 first: int = 0, step: int = 1, iterations: int = 20) -> np.ndarray:
    """:func:`refine_pose` for many key frames at once (in threads): (K, 3) ``poses`` with those of
    ``nodes`` (indices) fitted, each onto ``grid`` with its end points ``points_v[starts[k] + first:
    starts[k + 1]:step]`` ((N, 2) [m], vehicle frame; ``starts`` (K + 1,) row offsets); the other rows
    as given. Each fit is the very one :func:`refine_pose` makes, and kept under the same bounds."""
    start = np.asarray(poses, np.float64)
    fitted = start.copy()
    nodes = np.ascontiguousarray(nodes, np.int64)
    _refine_many(grid.values, float(grid.origin_m[0]), float(grid.origin_m[1]), 1.0 / grid.resolution_m,
                 np.ascontiguousarray(points_v, np.float64), np.ascontiguousarray(starts, np.int64), int(first),
                 int(step), nodes, fitted, iterations)
    moved = fitted[nodes] - start[nodes]
    too_far = ((np.hypot(moved[:, 0], moved[:, 1]) > REFINE_MAX_SHIFT_CELLS * grid.resolution_m)
               | (np.abs(moved[:, 2]) > REFINE_MAX_TURN_RAD))
    fitted[nodes[too_far]] = start[nodes[too_far]]
    return fitted
