"""Localising a drive in a saved map, without being told where it starts.

The map (:class:`~slam_engine.model.map_bundle.MapBundle`) is held as two blurred hit grids of its
key frames' end points at their poses: a coarse one (``localization.search_resolution_m``) for the
global search, the map's own cells for tracking and refinement. A *stretch* of the drive (its scans
over ``stretch_m`` of travel, joined by the drive's own relative poses: odometry, or another map's
key frames) is searched for over the whole map and every heading by branch and bound (Hess et al.
2016, Cartographer's global localisation), then refined; with ``from_places`` the best pose is searched
for only around the places the map's place index proposes and the runner-up over the whole map
(:func:`~slam_engine.backend.place_index.search_at_places`: the whole map's verdict where the index holds
the place, never a wrong placement where it does not). The placement counts only when it scores at
least ``min_score``, no pose elsewhere scores nearly as well, the next, disjoint stretch, searched
for on its own, lands where the scans tracked from the first placement put it, and no more than
``max_seen_through`` of the two stretches' returns fall where the map saw free space (:class:`FreeSpace`:
a look-alike building's walls stand in the map's rooms). From there each scan is
fitted locally from where the drive's own motion puts it, or searched for in a small window around
there, and scored only by its end points that fall where the saved map observed anything (a drive that
leaves the map is carried by its own motion, not judged against cells the map never saw, and is not lost
there: back in the map, it is tracked in a window grown with the travel since its last match). A scan
that matched counts as found only as :class:`TrackCheck` judges it against the found scans before it (a
sharp score drop, or returns where the map saw free space: a drive carried off to a look-alike place).
With no scan matched over ``lost_after_m`` of travel where the map could judge it, the drive is lost,
searched for near where its motion carried it and then over the whole map, and a match in the widened
window must score as a placement does. The drive's own scans are matched to each other on cells of
``local_map_resolution_m``, coarser than the map's (intel: as accurate, in less than half the time). A
drive that is never placed is refused (``localised`` False, with the best score found), not forced in.

Frames: ``map``: the bundle's; the drive's own frame: its odometry (or its map's) frame. Poses
``[x_m, y_m, theta_rad]``; points (N, 2) [m] in the vehicle frame.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from slam_engine.backend.correlative import (
    MatchGrid,
    angular_step_rad,
    fit_pose,
    mask_at,
    max_pyramid,
    refine_pose,
    search,
)
from slam_engine.backend.loop_closer import close_loops, thin
from slam_engine.backend.place_index import PlaceCandidate, PlaceIndex, map_places, search_at_places
from slam_engine.backend.pose_graph import Edge
from slam_engine.backend.submaps import match_grid_from_points
from slam_engine.config import LocalizationConfig, LoopClosingConfig, PlaceIndexConfig, SlamConfig
from slam_engine.errors import ConfigError
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.poses import compose, inverse, key_poses, place_each, place_points, relative, wrap_angle
from slam_engine.model.result import OccupancyGrid, Trajectory
from slam_engine.products.rendering import FREE_THRESHOLD

PLACE_QUERY_POINTS = 3000  # a stretch's end points that describe it to the place index, at most
MATCH_RANGE_M = 20.0  # end points farther than this are left out of matching (as the loop closer does)
TRACK_POINTS = 250  # a tracked scan is matched with at most this many end points
COARSE_LEVELS = 10  # the global grid's pyramid: blocks up to 512 cells (51 m at 0.1 m)
JOIN_WINDOW_M = 0.3  # a drive's scans are matched to those before it within this of its odometry [m]
JOIN_WINDOW_RAD = 0.3  # ... and this turn [rad]
JOIN_MIN_SCORE = 0.3  # ... and kept where the odometry puts them when the match scores lower
# a match on its window's edge (within a cell, or this turn [rad]) is searched for again around itself, up
# to this many times: aces-rough's odometry is off by up to 0.5 rad in one turn on the spot
JOIN_EDGE_RAD, JOIN_RECENTRES = 0.02, 2
JOIN_AMBIGUITY_M, JOIN_AMBIGUITY_RAD = 0.1, 0.05  # a second match this far from the best [m], [rad] ...
JOIN_RUNNER_UP = 0.95  # ... scoring this share of the best: ambiguous
JOIN_LINE_HALF_WIDTH_M, JOIN_LINE_HALF_WIDTH_RAD = 0.1, 0.03  # along a line this wide: a corridor
JOIN_POINTS = 3000  # the recent scans' end points a scan is matched against, at most
JOIN_REBUILD_M, JOIN_REBUILD_RAD = 0.3, 0.2  # their grid is built anew after this much motion [m], [rad]
JOIN_LEVELS = 4  # its pyramid: windows up to 15 cells a side
MAX_TRACK_WINDOW_M = 1.5  # the widest window a scan is tracked in, however long untracked [m]
MAX_TRACK_WINDOW_RAD = 0.6  # ... [rad]
FINE_LEVELS = 6
# a scan whose last one matched is first fitted locally (Levenberg-Marquardt from the prediction); the fit
# counts when it moved at most this far [m], [rad] and scores track_min_score, else the window is searched
FIT_TRUST_M, FIT_TRUST_RAD = 0.15, 0.05
COVERAGE_CELL_M = 0.1  # the map's observed area is kept on cells this large [m]
PLACES_COVERAGE_CELL_M = 0.2  # ... and rendered on cells this large for its places alone (which map) [m]
# a stretch is placed only where its last scan's origin lies within this of a cell the map observed: a
# vehicle is where its map saw free space (on intel-a's map that leaves a third of the map's bounding
# box, on aces-rough-a's a quarter) [m]
ORIGIN_REACH_M = 0.3
MIN_COVERED_SHARE = 0.5  # a scan with fewer of its end points on observed cells is not judged by the map
STRETCH_GROWTH = (1, 2, 4)  # an ambiguous stretch is searched for again this many times longer
HINT_WINDOW_M, HINT_WINDOW_RAD = 2.0, 0.5  # a start pose given as a hint is searched within [m], [rad]
# a lost drive is searched for near where its own motion carried it, in a window that grows REFIND_GROWTH
# times as fast as the tracking window with the travel since a scan last matched (up to the largest) ...
REFIND_GROWTH, MAX_REFIND_WINDOW_M = 2.0, 10.0
GLOBAL_AFTER_M = 100.0  # ... and over the whole map once it went this far [m] without a match
# the pose graph that smooths a localised drive: its scan-to-scan motions (sd grows with the step) ...
MOTION_SD_M, MOTION_SD_PER_M = 0.01, 0.05  # [m], [m/m]
MOTION_SD_RAD, MOTION_SD_RAD_PER_RAD, MOTION_SD_RAD_PER_M = 0.003, 0.05, 0.01  # [rad], [rad/rad], [rad/m]
# ... and each matched scan's place in the map
MAP_SD_M, MAP_SD_RAD = 0.05, 0.02  # the tracking grid's: windows up to 31 cells a side
# a drive's own loops are closed over key frames this far apart [m], [rad] (the mapper's default scheduling)
OWN_KEY_FRAME_M, OWN_KEY_FRAME_RAD = 0.2, 0.1
# a global search prunes below this share of min_score: a weaker placement is still reported as the best
# score of a refused drive, and pruning at min_score itself would leave it unknown
REPORT_SHARE = 0.9
# a tracked scan scoring below this share of the last found scan's is not found: a robot carried off (kidnapped)
# whose first scan there still fits where it was, weakly (0.55 after 1.00 in a made-up floor); the sharpest drop
# of a drive tracked in its own building was to 0.53 of the scan before (intel-b, once in 278) ...
SCORE_DROP_SHARE = 0.6
# ... or this share where more than max_seen_through of its returns fall in the map's free space (carried off in
# the office to a look-alike place: 0.67 after 1.00, a quarter of its returns seen through) ...
SEEN_DROP_SHARE = 0.8
# ... and after a drop, a scan is found again by tracking only once it scores this share of the level it dropped
# from (the office's look-alike places scored 0.4-0.84 after 1.00), else the drive is lost and searched for
RECOVER_SHARE = 0.9
# a tracked scan is judged with the scans matched over this much travel before it [m] (one scan's returns can fall
# on free space for a moment: people, a door, trees), when they hold this many end points on observed cells
SEEN_THROUGH_SPAN_M, SEEN_THROUGH_MIN_POINTS = 2.0, 100
REFUSED_MIN_POINTS = 30  # a scan that did not match, with fewer end points on observed cells, is not judged by them
# why a try at placing the drive failed (LocalizationResult.failed_tries, refusal_reason)
LOW_SCORE, AMBIGUOUS, NOT_CONFIRMED, TOO_SHORT = "scored too low", "ambiguous", "not confirmed", "drive too short"
SEEN_THROUGH = "seen through"
# localize_log with threads: the first try at placing the drive is made on its first scans, once this
# many stretches of travel are matched: the first stretch grown to its longest and the one confirming it
START_STRETCHES = 2 * STRETCH_GROWTH[-1] + 1


@dataclass
class FreeSpace:
    """Where the saved map saw free space well inside (at least ``margin_m`` from any cell not free):
    ``deep`` (H, W) bool on the map's cells of ``resolution_m`` from ``origin_m`` (map frame). A placed
    drive's returns there contradict the map: its beams ended where the map's saw through (a room of a
    look-alike building that is wider or elsewhere, a wall the map does not have), as the map's own
    consistency check (:mod:`slam_engine.evaluation.consistency`) judges a map's scans."""

    deep: np.ndarray
    origin_m: np.ndarray
    resolution_m: float

    @classmethod
    def of_grid(cls, grid: OccupancyGrid, margin_m: float) -> FreeSpace:
        """The deep free space of a rendered map ``grid``."""
        free_log_odds = math.log(FREE_THRESHOLD / (1.0 - FREE_THRESHOLD))
        free = (grid.log_odds != 0.0) & (grid.log_odds < free_log_odds)
        deep = free & ~cells_within(~free, grid.resolution_m, margin_m, closed=False)
        return cls(deep, np.array([grid.origin_x_m, grid.origin_y_m]), grid.resolution_m)

    def holds(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which map-frame points (N, 2) [m] fall in the deep free space."""
        return mask_at(self.deep, self.origin_m, self.resolution_m, points_m)


@dataclass
class Coverage:
    """Where the saved map has observed anything, free or occupied: ``observed`` (H, W) bool on cells of
    ``resolution_m`` from ``origin_m`` (map frame). A drive's end points outside it fall where the map
    cannot say whether they fit: a low match score there is no evidence against the pose."""

    observed: np.ndarray
    origin_m: np.ndarray
    resolution_m: float

    @classmethod
    def of_bundle(cls, bundle: MapBundle, cell_m: float) -> Coverage:
        """The bundle's scans rendered on cells of ``cell_m`` [m] (coarser than the map's and faster: cells a
        ray passes by at a corner may be left out)."""
        return cls.of_grid(rendered(bundle, max(cell_m, bundle.resolution_m)), 1)

    @classmethod
    def of_grid(cls, grid: OccupancyGrid, factor: int) -> Coverage:
        """The observed cells of a rendered map ``grid``, pooled ``factor`` times larger."""
        pooled = grid.pooled(factor)
        return cls(pooled.known(), np.array([pooled.origin_x_m, pooled.origin_y_m]), pooled.resolution_m)

    def covers(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which map-frame points (N, 2) [m] fall on observed cells."""
        return mask_at(self.observed, self.origin_m, self.resolution_m, points_m)

    def near_cells_of(self, grid: MatchGrid, reach_m: float) -> np.ndarray:
        """(H, W) bool on ``grid``'s cells: those whose centre lies within ``reach_m`` of an observed cell."""
        near = cells_within(self.observed, self.resolution_m, reach_m, closed=True)
        rows, cols = grid.values.shape
        ix, iy = np.meshgrid(np.arange(cols), np.arange(rows))
        centres = grid.origin_m + (np.stack([ix.ravel(), iy.ravel()], axis=1) + 0.5) * grid.resolution_m
        return mask_at(near, self.origin_m, self.resolution_m, centres).reshape(rows, cols)


@dataclass
class MapIndex:
    """A saved map as matching takes it: ``coarse`` for global searches, ``fine`` (the map's cells) for
    tracking and refinement, both in the map frame; ``coverage``: where the map observed anything;
    ``origins``: where on ``coarse`` a placed scan's origin may lie (a max pyramid, see
    :func:`~slam_engine.backend.correlative.search`)."""

    coarse: MatchGrid
    fine: MatchGrid
    coverage: Coverage
    origins: np.ndarray
    free: FreeSpace

    @classmethod
    def of_bundle(cls, bundle: MapBundle, config: LocalizationConfig) -> MapIndex:
        """The bundle's index."""
        points_m = map_points(bundle)
        coarse = match_grid_from_points(points_m, max(config.search_resolution_m, bundle.resolution_m), 1.0,
                                        n_levels=COARSE_LEVELS)
        fine = match_grid_from_points(points_m, bundle.resolution_m, 1.0, n_levels=FINE_LEVELS)
        grid = rendered(bundle, bundle.resolution_m)
        coverage = Coverage.of_grid(grid, max(1, int(round(COVERAGE_CELL_M / bundle.resolution_m))))
        origins = max_pyramid(coverage.near_cells_of(coarse, ORIGIN_REACH_M).astype(np.uint8), coarse.n_levels)
        return cls(coarse, fine, coverage, origins, FreeSpace.of_grid(grid, config.seen_through_margin_m))

    def seen_through(self, points_m: np.ndarray) -> tuple[int, int]:
        """(how many of them fall in the map's deep free space, how many on cells it observed) of end points
        (N, 2) [m, map frame]."""
        judged = points_m[self.coverage.covers(points_m)]
        return int(self.free.holds(judged).sum()), len(judged)


def cells_within(mask: np.ndarray, resolution_m: float, distance_m: float, closed: bool) -> np.ndarray:
    """(H, W) bool: the cells whose centre lies closer than ``distance_m`` [m] (``closed``: at most that far)
    to the centre of a True cell of ``mask`` (H, W; cells of ``resolution_m``): what thresholding the
    Euclidean distance transform of ``~mask`` gives (the same float comparisons), without it. The disc is
    taken row by row: a running maximum along x as wide as the disc is at that row offset, shifted by it.
    On a 4800 x 5440 map (the campus) 0.24-0.34 s against the transform's 1.3 s."""
    from scipy import ndimage

    def reaches(dx: int, dy: int) -> bool:
        apart_m = math.sqrt(dx * dx + dy * dy) * resolution_m
        return apart_m <= distance_m if closed else apart_m < distance_m

    h, w = mask.shape
    source = np.ascontiguousarray(mask, np.uint8)
    out = np.zeros((h, w), np.uint8)
    reach = int(math.floor(distance_m / resolution_m)) + 1
    for dy in range(-min(reach, h - 1), min(reach, h - 1) + 1):
        if not reaches(0, dy):
            continue
        half = max(dx for dx in range(reach + 1) if reaches(dx, dy))
        row = ndimage.maximum_filter1d(source, size=2 * half + 1, axis=1, mode="constant", cval=0) if half else source
        if dy >= 0:  # out[y] |= row[y + dy]
            np.bitwise_or(out[: h - dy], row[dy:], out=out[: h - dy])
        else:
            np.bitwise_or(out[-dy:], row[: h + dy], out=out[-dy:])
    return out.astype(bool)


def unmatched_below(config: LocalizationConfig) -> float:
    """The score below which a tracked scan's match counts as none (score 0): it would be found by no rule
    (``track_min_score``, ``nudge_min_score``, ``min_score``) nor held as a drop any differently
    (:meth:`TrackCheck.refused`: below SCORE_DROP_SHARE of any found scan's score). A search pruned there
    costs a scan that matches nowhere far less (aces-rough-b, 83 such scans: its localisation 0.82 -> 0.73 s)."""
    return SCORE_DROP_SHARE * min(config.track_min_score, config.nudge_min_score, config.min_score)


def rendered(bundle: MapBundle, resolution_m: float) -> OccupancyGrid:
    """The bundle's scans rendered as an occupancy grid on cells of ``resolution_m`` [m] (map frame)."""
    from slam_engine.backend.map_builder import render_occupancy
    from slam_engine.config import GridConfig

    return render_occupancy(bundle.scans(), bundle.poses, bundle.origin_v, GridConfig(resolution_m=resolution_m))


def map_points(bundle: MapBundle) -> np.ndarray:
    """Every end point of the saved map (N, 2) [m, map frame]; refuses a map that holds none."""
    hits = bundle.all_hits()
    owner = np.repeat(np.arange(len(bundle)), [len(h) for h in hits])
    points = np.concatenate(hits) if hits else np.zeros((0, 2))
    if len(points) == 0:
        raise ConfigError("the saved map holds no end points to localise against")
    return place_each(bundle.poses, points, owner)


def map_places_of(bundle: MapBundle, place_config: PlaceIndexConfig) -> PlaceIndex:
    """A saved map's places (:func:`~slam_engine.backend.place_index.map_places`): those the bundle keeps when
    they were laid out as ``place_config`` asks, else made now without its match grids (its lattice over the
    free space it observed on cells of PLACES_COVERAGE_CELL_M: ranking maps needs no finer)."""
    stored = bundle.places
    if stored is not None and stored.radius_m == place_config.radius_m and stored.spacing_m == place_config.spacing_m:
        return PlaceIndex.of_stored(stored)
    coverage = Coverage.of_bundle(bundle, PLACES_COVERAGE_CELL_M)
    return map_places(map_points(bundle), bundle.poses[:, :2], coverage.covers, place_config)


@dataclass(frozen=True)
class MapPlaces:
    """A saved map's place index and the settings of the searches around the places it proposes."""

    index: PlaceIndex
    config: PlaceIndexConfig
    candidates: int  # places proposed per stretch

    @classmethod
    def of(cls, bundle: MapBundle, config: SlamConfig) -> MapPlaces | None:
        """The bundle's places when ``localization.from_places`` asks for them (made only then), else None."""
        return cls.of_index(map_places_of(bundle, config.place_index), config) if config.localization.from_places \
            else None

    @classmethod
    def of_index(cls, index: PlaceIndex, config: SlamConfig) -> MapPlaces | None:
        """``index`` with the settings of ``config`` when ``localization.from_places`` asks for it, else None."""
        if not config.localization.from_places:
            return None
        return cls(index, config.place_index, config.localization.place_candidates)

    def proposed(self, drive: DriveScans, first: int, last: int) -> list[PlaceCandidate]:
        """The places the index proposes for the stretch ``first..last`` of ``drive``, best first (none
        when it describes too little)."""
        return self.index.query(drive.cloud(first, last, PLACE_QUERY_POINTS), self.candidates)


class TrackCheck:
    """Whether a scan that matched the map near where the drive's motion put it is where the drive is, judged
    against the scans found before it, as they come (forwards or backwards): a robot carried off to a place
    that looks like where it was goes on matching there, weakly, walls and all, but its furniture and doors
    stand where the map saw free space. A scan is not found

    - when its score drops below SCORE_DROP_SHARE of the last found scan's (SEEN_DROP_SHARE where more than
      ``max_seen_through`` of its returns fall in the map's free space, :meth:`MapIndex.seen_through`), nor
      after such a drop until a scan scores RECOVER_SHARE of the level it dropped from;
    - while the scans judged over the last SEEN_THROUGH_SPAN_M of travel, it among them, have more than
      ``max_seen_through_track`` of their returns in the map's free space."""

    def __init__(self, index: MapIndex, config: LocalizationConfig):
        self.index, self.config = index, config
        self.reset(None)

    def reset(self, score: float | None) -> None:
        """Start again from a scan placed with ``score`` (None: none found yet, or lost)."""
        self.found_score: float | None = score
        self.dropped_from: float | None = None
        self._window: deque[tuple[float, int, int]] = deque()  # judged scans: (travel, seen through, on the map)
        self._travel_m = 0.0

    def _seen_through(self, pose: np.ndarray, hits_v: np.ndarray, step_m: float) -> tuple[float, bool]:
        """(the share of a scan's returns ``hits_v`` (N, 2) [m, vehicle frame], placed at ``pose`` (map
        frame), in the map's free space, whether the scans judged over the last SEEN_THROUGH_SPAN_M have too
        many there); ``step_m``: its travel since the scan judged before [m]."""
        self._travel_m += abs(step_m)
        through, judged = self.index.seen_through(_placed_points(pose, hits_v))
        self._window.append((self._travel_m, through, judged))
        while self._window[0][0] < self._travel_m - SEEN_THROUGH_SPAN_M:
            self._window.popleft()
        all_through = sum(counts[1] for counts in self._window)
        all_judged = sum(counts[2] for counts in self._window)
        return (through / judged if judged else 0.0,
                all_judged >= SEEN_THROUGH_MIN_POINTS and all_through > self.config.max_seen_through_track * all_judged)

    def refused(self, score: float, pose: np.ndarray, hits_v: np.ndarray) -> None:
        """A scan the map could judge did not match (``score``, too low; ``hits_v``: its returns, ``pose``:
        where the drive's motion put it, map frame): a drop, held as :meth:`accepts` holds one, when it falls below
        SCORE_DROP_SHARE of the last found scan's and more than ``max_seen_through`` of its returns fall in
        the map's free space (the first scan of a robot carried off, too unlike where it was to match)."""
        if self.dropped_from is not None or self.found_score is None or score >= SCORE_DROP_SHARE * self.found_score:
            return
        through, judged = self.index.seen_through(_placed_points(pose, hits_v))
        if judged >= REFUSED_MIN_POINTS and through > self.config.max_seen_through * judged:
            self.dropped_from = self.found_score

    def accepts_placement(self, score: float, pose: np.ndarray, hits_v: np.ndarray, step_m: float) -> bool:
        """Whether a scan matched in a lost drive's widened window (scoring a placement's ``min_score``) is
        found: judged afresh, no more than ``max_seen_through`` of its returns in the map's free space (a
        placement's bar); records it when it is."""
        self.reset(None)
        share, _ = self._seen_through(pose, hits_v, step_m)
        if share > self.config.max_seen_through:
            return False
        self.found_score = score
        return True

    def accepts(self, score: float, pose: np.ndarray, hits_v: np.ndarray, step_m: float) -> bool:
        """Whether a scan that matched with ``score`` at ``pose`` (map frame; its returns ``hits_v``, vehicle
        frame; travel ``step_m`` since the scan judged before) is found (the class docstring); records it
        when it is."""
        share, contradicted = self._seen_through(pose, hits_v, step_m)
        if self.dropped_from is not None:
            if score < RECOVER_SHARE * self.dropped_from:
                return False
            self.dropped_from = None
        elif self.found_score is not None:
            drop = SEEN_DROP_SHARE if share > self.config.max_seen_through else SCORE_DROP_SHARE
            if score < drop * self.found_score:
                self.dropped_from = self.found_score
                return False
        if contradicted:
            return False
        self.found_score = score
        return True


def _placed_points(pose: np.ndarray, hits_v: np.ndarray) -> np.ndarray:
    """A scan's returns (N, 2) [m, vehicle frame] thinned as tracking takes them, placed at ``pose`` (map
    frame)."""
    return place_points(pose, thin(hits_v, TRACK_POINTS))


@dataclass
class DriveScans:
    """A drive as localisation takes it: ``t_s`` (S,) [s], ``poses`` (S, 3) in the drive's own frame
    (odometry, or its map's key frames), ``hits`` (S lists of (B, 2) [m], vehicle frame), ``origin_v``
    (2,): the LiDAR's position in the vehicle frame [m], where its beams start."""

    t_s: np.ndarray
    poses: np.ndarray
    hits: list[np.ndarray]
    origin_v: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        steps = np.hypot(*np.diff(self.poses[:, :2], axis=0).T) if len(self.poses) > 1 else np.zeros(0)
        self.travel_m = np.concatenate([[0.0], np.cumsum(steps)])
        self.reached_end = False  # whether a stretch asked for ran to the last scan (see localize_log)

    def __len__(self) -> int:
        return len(self.t_s)

    @classmethod
    def from_log(cls, log: DriveLog, config: SlamConfig, on_start: Callable[[DriveScans], None] | None = None,
                 start_m: float = 0.0) -> DriveScans:
        """Every scan of ``log`` at its dead-reckoned pose, with its returned end points, matched to each
        other (:meth:`scan_matched`); ``on_start`` hears the drive's first ``start_m`` of travel as soon as
        those scans are matched (the whole drive, when shorter)."""
        from slam_engine.frontend.odometry import dead_reckoning
        from slam_engine.frontend.particle_filter import make_projector

        if log.scans is None or log.lidar is None or len(log.scans) == 0:
            raise ConfigError("the log has no LiDAR scans: there is nothing to localise with")
        odometry = dead_reckoning(log)
        projector = make_projector(log.lidar, config, no_return_bounded=False)
        offsets = np.zeros(len(log.scans)) if log.scans.angle_offset_rad is None else log.scans.angle_offset_rad
        hits = [projector.project(ranges, angle_offset_rad=float(offset)).hits_v
                for ranges, offset in zip(log.scans.ranges_m, offsets, strict=True)]
        drive = cls(np.asarray(odometry.t_s, np.float64), np.asarray(odometry.poses, np.float64), hits,
                    np.asarray(projector.origin_v, np.float64))
        return drive.scan_matched(config.localization.local_map_resolution_m, config.localization.local_map_m,
                                  on_start, start_m)

    @classmethod
    def from_bundle(cls, bundle: MapBundle) -> DriveScans:
        """Another map's key frames at their poses in that map (for merging two maps)."""
        return cls(bundle.t_s.copy(), bundle.poses.copy(), bundle.all_hits(), np.asarray(bundle.origin_v, np.float64))

    def stretch_end(self, first: int, stretch_m: float) -> int:
        """The last scan of the stretch that starts at ``first`` and spans ``stretch_m`` of travel."""
        end = int(np.searchsorted(self.travel_m, self.travel_m[first] + stretch_m, side="left"))
        end = min(max(end, first), len(self) - 1)
        self.reached_end |= end == len(self) - 1
        return end

    def cloud(self, first: int, last: int, budget: int) -> np.ndarray:
        """The end points of scans ``first..last`` in scan ``last``'s vehicle frame (N, 2) [m], joined by
        the drive's relative poses and thinned to ``budget``."""
        frames = np.arange(first, last + 1)
        in_reach = [h[np.hypot(h[:, 0], h[:, 1]) <= MATCH_RANGE_M] for h in (self.hits[k] for k in frames)]
        counts = [len(h) for h in in_reach]
        if sum(counts) == 0:
            return np.zeros((0, 2))
        placed = place_each(relative(self.poses[last], self.poses[frames]), np.concatenate(in_reach),
                            np.repeat(np.arange(len(frames)), counts))
        return np.ascontiguousarray(thin(placed, budget))

    def scan_matched(self, resolution_m: float, span_m: float, on_start: Callable[[DriveScans], None] | None = None,
                     start_m: float = 0.0) -> DriveScans:
        """The drive with its relative poses corrected as a front end would: each scan matched (on
        ``resolution_m`` cells) against the scans of the last ``span_m`` of travel before it, from where
        the odometry puts it. A wheel odometry's turn errors (intel: 0.13 rad between scans at the 90th
        percentile) would otherwise smear every stretch and every prediction. ``on_start`` hears the
        first scans matched, once they span ``start_m`` of travel (all of them, when the drive is
        shorter): each scan's match depends only on the scans before it."""
        joiner = ScanJoiner(resolution_m, span_m)
        for k in range(len(self)):
            joiner.add(self.poses[k], self.hits[k])
            if on_start is not None and joiner.travel_m >= start_m:
                on_start(DriveScans(self.t_s[: k + 1], np.array(joiner.poses), self.hits[: k + 1], self.origin_v))
                on_start = None
        matched = DriveScans(self.t_s, np.array(joiner.poses), self.hits, self.origin_v)
        if on_start is not None:
            on_start(matched)
        return matched


class ScanJoiner:
    """A drive's scans matched, as they come, to the scans of its last ``span_m`` of travel (on cells of
    ``resolution_m``), each from where its odometry puts it (:meth:`DriveScans.scan_matched`; a live
    localisation feeds it scan by scan). ``poses``: every scan's matched pose so far, in the drive's own
    frame (the first scan's odometry pose is its origin); ``travel_m``: the travel they span."""

    def __init__(self, resolution_m: float, span_m: float):
        self.resolution_m, self.span_m = resolution_m, span_m
        self.poses: list[np.ndarray] = []
        self.travel_m = 0.0
        self._travel: list[float] = []  # of the scans still within span_m of the last one
        self._placed: list[np.ndarray] = []  # their end points in the drive's frame
        self._grid: MatchGrid | None = None
        self._built_at = np.zeros(3)
        self._odometry = np.zeros(3)  # the last scan's odometry pose

    def add(self, odometry_pose: np.ndarray, hits_v: np.ndarray) -> np.ndarray:
        """The next scan's matched pose (drive frame) from its odometry pose and its returns (N, 2) [m,
        vehicle frame]."""
        odometry_pose = np.asarray(odometry_pose, np.float64)
        in_reach = hits_v[np.hypot(hits_v[:, 0], hits_v[:, 1]) <= MATCH_RANGE_M]
        if not self.poses:
            pose = odometry_pose.copy()
        else:
            last = self.poses[-1]
            pose = compose(last, relative(self._odometry, odometry_pose))
            points = np.ascontiguousarray(thin(in_reach, TRACK_POINTS), np.float64)
            moved = relative(self._built_at, last)
            if (self._grid is None or math.hypot(moved[0], moved[1]) >= JOIN_REBUILD_M
                    or abs(moved[2]) >= JOIN_REBUILD_RAD):
                first = int(np.searchsorted(self._travel, self._travel[-1] - self.span_m, side="left"))
                del self._travel[:first], self._placed[:first]  # beyond the span: never needed again
                recent = np.concatenate(self._placed)
                self._grid = (match_grid_from_points(thin(recent, JOIN_POINTS), self.resolution_m, 1.0,
                                                     n_levels=JOIN_LEVELS) if len(recent) >= 20 else None)
                self._built_at = last
            if len(points) >= 5 and self._grid is not None:
                pose = _joined(self._grid, points, pose)
            self.travel_m += float(np.hypot(*(pose[:2] - last[:2])))
        self.poses.append(pose)
        self._travel.append(self.travel_m)
        self._placed.append(place_points(pose, in_reach))
        self._odometry = odometry_pose
        return pose


@dataclass(frozen=True)
class Near:
    """Where a scan is thought to be in the map: a ``pose`` and how far off it may be (``window_m``,
    ``window_rad``)."""

    pose: np.ndarray
    window_m: float
    window_rad: float

    def __iter__(self):  # unpacks as search() takes it: (initial pose, window_m, window_rad)
        return iter((np.asarray(self.pose, np.float64), self.window_m, self.window_rad))

    def moved(self, drive: DriveScans, first: int, last: int) -> Near:
        """The same belief carried from scan ``first`` to scan ``last`` by the drive's own motion."""
        return Near(compose(self.pose, relative(drive.poses[first], drive.poses[last])), self.window_m,
                    self.window_rad)


@dataclass(frozen=True)
class OwnLoops:
    """How a drive's own loops are closed (the back end's settings, :func:`close_loops`): the loop closer's
    ``config``, its cells ``resolution_m`` and the place index's settings for far searches (None: whole map)."""

    config: LoopClosingConfig
    resolution_m: float
    places: PlaceIndexConfig | None = None

    @classmethod
    def of(cls, config: SlamConfig) -> OwnLoops | None:
        """The loop closing ``config`` asks for, or None where ``localization.own_loops`` is off."""
        if not config.localization.own_loops:
            return None
        return cls(config.loop_closing, config.grid.resolution_m, config.place_index.for_far_searches())


@dataclass
class LocalizationResult:
    """Where a drive was in a saved map: ``localised``; ``trajectory`` (its scans in the map frame, None
    when refused) with each pose's ``confidence`` (its match score, 0-1) and whether it was ``tracked``
    (matched) or carried by the odometry; ``events``: when it was found and lost; ``best_score``: the
    best global placement score seen (also when refused); ``T_map_from_drive``: the drive's own frame in
    the map at its first placement; ``outside_map``: the scans too far out of the saved map's observed
    area to be judged by it (carried by the drive's own motion)."""

    localised: bool
    best_score: float
    trajectory: Trajectory | None = None
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tracked: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    events: list[dict] = field(default_factory=list)
    T_map_from_drive: np.ndarray | None = None
    outside_map: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    global_searches: int = 0
    own_closures: int = 0  # the drive's own loop closures the smoothing took (OwnLoops)
    failed_tries: dict[str, int] = field(default_factory=dict)  # why tries at a first placement failed: count
    wall_time_s: float = 0.0
    search_s: float = 0.0  # of wall_time_s: placing and tracking the drive (the rest: its scans, the map's index)
    whole_map_searches: int = 0  # of global_searches, over the whole map (no place proposed, or no index used)

    def summary(self) -> dict:
        tracked = self.tracked
        return {
            "localised": self.localised, "best_score": round(self.best_score, 4),
            "scans": int(len(self.confidence)), "scans_tracked": int(tracked.sum()),
            "scans_outside_map": int(self.outside_map.sum()),
            "mean_confidence": round(float(self.confidence.mean()), 4) if len(self.confidence) else None,
            "events": self.events, "global_searches": self.global_searches,
            "whole_map_searches": self.whole_map_searches, "own_loop_closures": self.own_closures,
            "failed_tries": dict(self.failed_tries),
            "T_map_from_drive": None if self.T_map_from_drive is None else [round(float(v), 5)
                                                                          for v in self.T_map_from_drive],
            "wall_time_s": round(self.wall_time_s, 3),
        }


class Localizer:
    """Places and tracks one drive in one saved map (see the module docstring)."""

    def __init__(self, index: MapIndex, drive: DriveScans, config: LocalizationConfig, threads: int = 1,
                 own_loops: OwnLoops | None = None, places: MapPlaces | None = None):
        self.index = index
        self.drive = drive
        self.config = config
        self.threads = max(1, int(threads))
        self.own_loops = own_loops
        self.places = places  # where a stretch is searched for first (None: the whole map)
        self.best_score = 0.0
        self.global_searches = 0
        self.whole_map_searches = 0  # of global_searches, over the whole map: no place proposed
        self.uncovered = np.zeros(len(drive), bool)  # scans too far out of the map to be judged by it
        self.failed_tries: dict[str, int] = {}  # why each first try failed (LOW_SCORE, ...): how many
        self._why = ""  # why the last placed_stretch or confirmed_placement found nothing
        self.check = TrackCheck(index, config)  # whether a matched scan is found, as step() tracks

    # --- global placement -------------------------------------------------------------------
    def place_stretch(self, first: int, last: int, near: Near | None = None) -> tuple[np.ndarray | None, bool]:
        """Scan ``last``'s pose in the map from the stretch ``first..last`` searched over the whole map
        (or ``near`` a map pose of scan ``last``), refined on the map's cells, and False; None when no pose
        scores ``min_score``, and whether another one, elsewhere, scores nearly as well. Over the whole map
        with ``places``, the best pose is searched for around the places they propose only (see
        :func:`~slam_engine.backend.place_index.search_at_places`)."""
        c = self.config
        cloud = self.drive.cloud(first, last, c.max_points)
        if len(cloud) < 20:
            return None, False
        if near is None:
            initial, window_m = self.index.coarse.centre_and_reach()
            window_rad = math.pi
        else:
            initial, window_m, window_rad = near
        self.global_searches += 1
        floor = c.min_score * REPORT_SHARE
        places = self.places if near is None else None
        proposed = places.proposed(self.drive, first, last) if places is not None else []
        if places is not None and proposed:
            match = search_at_places(self.index.coarse, cloud, initial, window_m, window_rad, proposed,
                                     places.config.window_m, places.config.window_rad, floor, c.ambiguity_m,
                                     c.ambiguity_rad, c.runner_up_ratio, floor, c.min_score, self.threads,
                                     self.index.origins)
        else:
            self.whole_map_searches += near is None
            match = search(self.index.coarse, cloud, initial, window_m, window_rad, floor, ambiguity_m=c.ambiguity_m,
                           ambiguity_rad=c.ambiguity_rad, runner_up_share=c.runner_up_ratio,
                           runner_up_min_score=floor, threads=self.threads, runner_up_from=c.min_score,
                           origins=self.index.origins, any_runner_up=True)
        if match is None:
            return None, False
        self.best_score = max(self.best_score, match.score)
        if match.score < c.min_score:
            return None, False
        if match.runner_up_score >= c.runner_up_ratio * match.score:
            return None, True
        return self.refined_placement(cloud, match.pose), False

    def refined_placement(self, cloud: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """A global match on the coarse grid's lattice (``pose``) fitted on the map's own cells: kept
        where the fit stays within a coarse cell and an angular step of it."""
        fitted = fit_pose(self.index.fine, cloud, pose)
        moved = fitted - pose
        coarse_m = self.index.coarse.resolution_m
        if (math.hypot(moved[0], moved[1]) > 1.5 * coarse_m
                or abs(float(wrap_angle(moved[2]))) > 1.5 * angular_step_rad(cloud, coarse_m)):
            return pose
        return fitted

    # --- tracking -----------------------------------------------------------------------------
    def track(self, k: int, predicted: np.ndarray, untracked_m: float = 0.0) -> tuple[np.ndarray, float]:
        """Scan k's pose near ``predicted`` (map frame) and its match score over its end points that fall
        on the map's observed cells; the window widens with the travel since a scan last matched
        (``untracked_m``). The score is NaN when too few of them do (nothing to judge the pose by)."""
        points = np.ascontiguousarray(thin(self.drive.hits[k], TRACK_POINTS), np.float64)
        if len(points) < 5:
            return predicted, 0.0
        covered = self.index.coverage.covers(place_points(predicted, points))
        if covered.mean() < MIN_COVERED_SHARE:
            return predicted, math.nan
        points = np.ascontiguousarray(points[covered])
        c = self.config
        if untracked_m == 0.0:  # the last scan matched: the prediction is close, a local fit finds it
            fitted = fit_pose(self.index.fine, points, predicted)
            moved = fitted - predicted
            if math.hypot(moved[0], moved[1]) <= FIT_TRUST_M and abs(float(wrap_angle(moved[2]))) <= FIT_TRUST_RAD:
                check = search(self.index.fine, points, fitted, self.index.fine.resolution_m,
                               angular_step_rad(points, self.index.fine.resolution_m), 0.0)
                if check is not None and check.score >= c.track_min_score:
                    return fitted, check.score
        window_m = min(c.track_window_m + c.window_per_m * untracked_m, MAX_TRACK_WINDOW_M)
        window_rad = min(c.track_window_rad + c.window_rad_per_m * untracked_m, MAX_TRACK_WINDOW_RAD)
        match = search(self.index.fine, points, predicted, window_m, window_rad, unmatched_below(c))
        if match is None:
            return predicted, 0.0
        return refine_pose(self.index.fine, points, match.pose), match.score

    def step(self, poses: np.ndarray, confidence: np.ndarray, tracked: np.ndarray, k: int, from_k: int,
             untracked_m: float = 0.0) -> None:
        """Place scan k from scan ``from_k``'s map pose and the drive's relative motion, tracked."""
        predicted = compose(poses[from_k], relative(self.drive.poses[from_k], self.drive.poses[k]))
        pose, score = self.track(k, predicted, untracked_m)
        c = self.config
        moved = pose - predicted
        hits, step_m = self.drive.hits[k], float(self.drive.travel_m[k] - self.drive.travel_m[from_k])
        if untracked_m > c.lost_after_m:  # lost, in a wide window: a match there is a placement
            ok = score >= c.min_score and self.check.accepts_placement(score, pose, hits, step_m)
        else:
            nudged = math.hypot(moved[0], moved[1]) <= c.nudge_m and abs(float(wrap_angle(moved[2]))) <= c.nudge_rad
            ok = score >= c.track_min_score or (score >= c.nudge_min_score and nudged)
            ok = ok and self.check.accepts(score, pose, hits, step_m)
        poses[k] = pose if ok else predicted
        self.uncovered[k] = math.isnan(score)
        confidence[k], tracked[k] = (0.0 if self.uncovered[k] else score), ok

    def placed_stretch(self, first: int, near: Near | None = None) -> tuple[int, np.ndarray] | None:
        """(last, map pose of scan ``last``) of the shortest stretch from ``first`` that places
        unambiguously: ``stretch_m`` of travel, twice and four times that while the placement is
        ambiguous (aces-rough's corridors: 4 m of them fit several places of the building almost as
        well). ``near``: where scan ``first`` is thought to be, if known (else the whole map)."""
        drive, previous = self.drive, -1
        for growth in STRETCH_GROWTH:
            last = drive.stretch_end(first, self.config.stretch_m * growth)
            if last == previous:
                self._why = TOO_SHORT if growth == STRETCH_GROWTH[0] else AMBIGUOUS  # the drive ends
                return None
            previous = last
            pose, ambiguous = self.place_stretch(first, last, None if near is None else near.moved(drive, first, last))
            if pose is not None:
                return last, pose
            if not ambiguous:
                self._why = LOW_SCORE
                return None
        self._why = AMBIGUOUS
        return None

    def confirmed_placement(self, first: int, near: Near | None) -> tuple[int, int, np.ndarray] | None:
        """(first, last, map pose of scan ``last``) of the stretch at ``first`` when a second, disjoint
        stretch after it, searched for on its own, is placed where tracking from it leads; None
        otherwise. ``near``: where scan ``first`` is thought to be (both searches stay near it)."""
        c, drive = self.config, self.drive
        placed = self.placed_stretch(first, near)
        if placed is None or placed[0] + 1 >= len(drive):
            self._why = self._why if placed is None else TOO_SHORT  # not placed, or too short to confirm it
            return None
        last, pose = placed
        confirming = self.placed_stretch(last + 1, None if near is None else near.moved(drive, first, last + 1))
        self._why = NOT_CONFIRMED
        if confirming is None:
            return None
        second_last, second = confirming
        poses = np.full((len(drive), 3), np.nan)
        confidence, tracked = np.zeros(len(drive)), np.zeros(len(drive), bool)
        poses[last] = pose
        self.check.reset(None)
        for k in range(last + 1, second_last + 1):
            self.step(poses, confidence, tracked, k, k - 1)
        gap = poses[second_last] - second
        if math.hypot(gap[0], gap[1]) > c.agree_m or abs(float(wrap_angle(gap[2]))) > c.agree_rad:
            return None
        through, judged = (a + b for a, b in zip(self.seen_through(first, last, pose),
                                                 self.seen_through(last + 1, second_last, second), strict=True))
        if through > c.max_seen_through * judged:
            self._why = SEEN_THROUGH
            return None
        return first, last, pose

    def seen_through(self, first: int, last: int, pose: np.ndarray) -> tuple[int, int]:
        """(how many of them fall in the map's deep free space, how many on cells it observed) of the end
        points of the stretch ``first..last`` placed with scan ``last`` at ``pose`` (map frame)."""
        return self.index.seen_through(place_points(pose, self.drive.cloud(first, last, self.config.max_points)))

    def first_tries(self) -> list[int]:
        """The scans whose stretches are searched for the first placement, in order: every stretch's first
        scan, or ``max_first_tries`` of them spread evenly over the drive (the first one always), so that
        a drive that is not in the map is refused in bounded time wherever it starts."""
        starts, k = [], 0
        while k < len(self.drive):
            starts.append(k)
            k = self.drive.stretch_end(k, self.config.stretch_m) + 1
        if len(starts) <= self.config.max_first_tries:
            return starts
        picks = np.linspace(0, len(starts) - 1, self.config.max_first_tries).round().astype(int)
        return [starts[i] for i in sorted(set(picks.tolist()))]

    def first_try(self, k: int, hint: np.ndarray | None) -> tuple[int, int, np.ndarray] | None:
        """:meth:`confirmed_placement` of the stretch at scan ``k``, searched near ``hint`` (the map pose
        of the drive's first scan) when given."""
        near = None if hint is None else Near(hint, HINT_WINDOW_M, HINT_WINDOW_RAD).moved(self.drive, 0, k)
        placement = self.confirmed_placement(k, near)
        if placement is None:
            self.failed_tries[self._why] = self.failed_tries.get(self._why, 0) + 1
        return placement

    def run(self, hint: np.ndarray | None = None, tried: dict[int, tuple[int, int, np.ndarray] | None] | None = None
            ) -> LocalizationResult:
        """Localise the whole drive; ``hint``: the map pose of its first scan, if known (searched within
        ``HINT_WINDOW_M`` / ``HINT_WINDOW_RAD`` of it, still confirmed); ``tried``: first tries already
        made (:meth:`first_try` by scan), whose outcome is taken as it is."""
        started = time.perf_counter()
        drive = self.drive
        n = len(drive)
        poses = np.full((n, 3), np.nan)
        confidence, tracked = np.zeros(n), np.zeros(n, bool)
        events: list[dict] = []
        placement = None
        for k in self.first_tries():  # the first placement
            placement = tried[k] if tried is not None and k in tried else self.first_try(k, hint)
            if placement is not None:
                break
        if placement is None:
            return LocalizationResult(False, self.best_score, events=events, global_searches=self.global_searches,
                                      failed_tries=dict(self.failed_tries), wall_time_s=time.perf_counter() - started,
                                      whole_map_searches=self.whole_map_searches)
        _, last, pose = placement
        poses[last] = pose
        self.check.reset(None)
        self.step(poses, confidence, tracked, last, last)
        events.append({"event": "found", "t_s": round(float(drive.t_s[last]), 3), "scan": last})
        travel = drive.travel_m
        last_tracked = last
        self.check.reset(confidence[last] if tracked[last] else None)
        for j in range(last - 1, -1, -1):  # the scans before it, tracked backwards
            self.step(poses, confidence, tracked, j, j + 1, float(travel[last_tracked] - travel[j + 1]))
            last_tracked = j if tracked[j] else last_tracked
        self.check.reset(confidence[last] if tracked[last] else None)
        jumps = self._track_forward(poses, confidence, tracked, last + 1, events)
        closures = self.own_closures(tracked, jumps)
        poses = self.smoothed(poses, tracked, jumps, closures)
        T_map_from_drive = _rigid_placement(poses[tracked], drive.poses[tracked])
        return LocalizationResult(True, self.best_score, Trajectory(drive.t_s.copy(), poses), confidence, tracked,
                                  events, T_map_from_drive, self.uncovered.copy(), self.global_searches,
                                  len(closures), dict(self.failed_tries), time.perf_counter() - started,
                                  whole_map_searches=self.whole_map_searches)

    def _track_forward(self, poses: np.ndarray, confidence: np.ndarray, tracked: np.ndarray, start: int,
                       events: list[dict]) -> list[int]:
        """Track every scan from ``start`` on. With no scan matched over ``lost_after_m`` of travel over
        scans the map could judge (outside its observed area a drive is not lost) the drive is lost: it
        is still carried by its own motion and tracked in a widening window, and each stretch is also
        searched for over the whole map; a confirmed placement puts it there (a jump). Returns the scans
        placed by a jump."""
        c, drive = self.config, self.drive
        travel = drive.travel_m
        last_tracked = start - 1
        lost = carried_off = False
        unmatched_m = 0.0  # travel since scan last_tracked over scans the map could judge but did not match [m]
        next_search = start
        jumps: list[int] = []
        k = start
        while k < len(drive):
            self.step(poses, confidence, tracked, k, k - 1, float(travel[k - 1] - travel[last_tracked]))
            if not tracked[k] and not self.uncovered[k]:  # a kidnap's first scans can fit too badly to be tracked
                self.check.refused(float(confidence[k]), poses[k], drive.hits[k])
            if tracked[k]:
                last_tracked, unmatched_m = k, 0.0
                if lost:
                    lost = False
                    events.append({"event": "found", "t_s": round(float(drive.t_s[k]), 3), "scan": k})
                k += 1
                continue
            if not self.uncovered[k] or self.check.dropped_from is not None:  # since a sharp drop, where its
                unmatched_m += float(travel[k] - travel[k - 1])  # motion carries it says nothing
            if not lost and unmatched_m > c.lost_after_m:
                lost = True
                events.append({"event": "lost", "t_s": round(float(drive.t_s[k]), 3), "scan": k})
                next_search = k + 1
                carried_off = self.check.dropped_from is not None  # lost since a sharp drop: a kidnap
            if lost and k >= next_search:
                untracked_m = float(travel[k] - travel[last_tracked])
                near = None if carried_off or untracked_m > GLOBAL_AFTER_M else Near(
                    poses[k], min(c.track_window_m + c.window_per_m * untracked_m * REFIND_GROWTH, MAX_REFIND_WINDOW_M),
                    min(c.track_window_rad + c.window_rad_per_m * untracked_m * REFIND_GROWTH, math.pi))
                placement = self.confirmed_placement(k, near)
                next_search = drive.stretch_end(k, c.stretch_m) + 1
                if placement is not None:
                    _, at, pose = placement
                    for j in range(k + 1, at + 1):  # carried to the placed scan, then placed there
                        self.step(poses, confidence, tracked, j, j - 1, c.lost_after_m)
                    poses[at] = pose
                    self.check.reset(None)
                    self.step(poses, confidence, tracked, at, at)
                    if near is None:
                        jumps.append(at)
                    lost, last_tracked, unmatched_m, k = False, at, 0.0, at
                    events.append({"event": "found", "t_s": round(float(drive.t_s[at]), 3), "scan": at})
            k += 1
        return jumps

    def own_closures(self, tracked: np.ndarray, jumps: list[int]) -> list[Edge]:
        """The drive's own loop closures (edges between its scans, in its own frame), found by the back
        end's loop closer over its key frames at the drive's scan-matched poses, when it went at least
        ``own_loops_after_m`` without a scan matching the map (a drive that stays in the map needs none);
        none where :class:`OwnLoops` is off. Across a jump (the drive lost and placed anew) the drive's
        own motion is not trusted: its key frames are closed in pieces between jumps."""
        loops, drive = self.own_loops, self.drive
        if loops is None or _longest_untracked_m(tracked, drive.travel_m) < self.config.own_loops_after_m:
            return []
        out: list[Edge] = []
        bounds = [0, *sorted(jumps), len(drive)]
        for start, end in zip(bounds[:-1], bounds[1:], strict=True):
            frames = start + key_poses(drive.poses[start:end], OWN_KEY_FRAME_M, OWN_KEY_FRAME_RAD)
            if len(frames) < 3:
                continue
            found = close_loops(drive.poses[frames], [drive.hits[k] for k in frames], loops.config, loops.resolution_m,
                                threads=self.threads, places=loops.places)
            out += [Edge(int(frames[e.i]), int(frames[e.j]), e.T_i_from_j, e.sigmas, e.loss, e.loss_scale)
                    for e in found.edges if abs(e.j - e.i) != 1]  # the rest: its motions, which the drive has
        return out

    def smoothed(self, poses: np.ndarray, tracked: np.ndarray, jumps: list[int], closures: Sequence[Edge] = ()
                 ) -> np.ndarray:
        """The drive's poses from one pose graph: the drive's own scan-to-scan motions, its own loop
        ``closures`` (:meth:`own_closures`) and each matched scan's place in the map (under a robust loss,
        so a wrong match lets go), as Cartographer's pure localisation ties its local trajectory to the
        frozen map. A stretch the map does not cover (a room the map never saw) is then held at both ends
        instead of dead-reckoned from one: intel-b in intel-a's map, whose drive crosses the building's
        middle, which intel-a never entered; where the drive loops out there, its closures hold it too
        (aces-rough-b). Motions into the scans in ``jumps`` (placed anew after the drive was lost) are
        left loose."""
        from slam_engine.backend.pose_graph import PoseGraph

        n = len(poses)
        if not tracked.any():
            return poses
        graph = PoseGraph(np.vstack([np.zeros(3), poses]), cauchy_scale=1.0)  # node 0: the map's origin
        for k in range(1, n):
            motion = relative(self.drive.poses[k - 1], self.drive.poses[k])
            d = math.hypot(motion[0], motion[1])
            sd_m = MOTION_SD_M + MOTION_SD_PER_M * d
            sd_rad = MOTION_SD_RAD + MOTION_SD_RAD_PER_RAD * abs(float(motion[2])) + MOTION_SD_RAD_PER_M * d
            if k in jumps:
                sd_m, sd_rad = 10.0, 1.0
            graph.add_edge(k, k + 1, motion, np.array([sd_m, sd_m, sd_rad]))
        for edge in closures:  # as the loop closer weighed them
            graph.add_edge(edge.i + 1, edge.j + 1, edge.T_i_from_j, edge.sigmas, robust=edge.robust)
        for matched in np.flatnonzero(tracked).tolist():
            graph.add_edge(0, matched + 1, poses[matched], np.array([MAP_SD_M, MAP_SD_M, MAP_SD_RAD]), robust=True)
        return graph.optimize(graph.optimize(robust=False))[1:]


def _longest_untracked_m(tracked: np.ndarray, travel_m: np.ndarray) -> float:
    """The longest travel [m] between two scans with no scan that matched the map between them (the
    drive's start and end count as such scans)."""
    marks = np.concatenate([[travel_m[0]], travel_m[tracked], [travel_m[-1]]]) if len(travel_m) else np.zeros(1)
    return float(np.max(np.diff(marks))) if len(marks) > 1 else 0.0


def _rigid_placement(map_poses: np.ndarray, drive_poses: np.ndarray) -> np.ndarray:
    """The drive's frame in the map (3,) that best carries its matched scans' own poses onto their map
    poses (least squares on positions; the heading as their mean turn)."""
    from slam_engine.evaluation.metrics import align_rigid_2d

    if len(map_poses) < 2:
        return compose(map_poses[0], inverse(drive_poses[0]))
    rotation, translation = align_rigid_2d(drive_poses[:, :2], map_poses[:, :2])
    turn = math.atan2(rotation[1, 0], rotation[0, 0])
    return np.array([translation[0], translation[1], turn])


def _joined(grid: MatchGrid, points: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Where ``points`` (a scan, vehicle frame) fit ``grid`` (the drive's recent scans) near ``predicted``:
    the best match refined; along a corridor, where poses along a line fit as well (Olson's ambiguity
    test, as the loop closer makes it), only across it and in heading, the odometry keeping its place
    along the line; ``predicted`` itself where nothing fits or the match is ambiguous otherwise. With
    aces-rough's scans a metre apart, taking the best match along its corridors put 10 % of the steps
    0.2-0.35 m off (the window's edge); odometry alone is off by about 5 % of the step there. A match on
    the window's edge is searched for again around itself: aces-rough-b's scan 140, whose odometry turn
    is 0.52 rad off, was joined 0.22 rad off, and the smoothing then trusted that over the map's match."""
    centre = predicted
    for _ in range(1 + JOIN_RECENTRES):
        match = search(grid, points, centre, JOIN_WINDOW_M, JOIN_WINDOW_RAD, JOIN_MIN_SCORE,
                       ambiguity_m=JOIN_AMBIGUITY_M, ambiguity_rad=JOIN_AMBIGUITY_RAD, runner_up_share=JOIN_RUNNER_UP,
                       line_half_width_m=JOIN_LINE_HALF_WIDTH_M, line_half_width_rad=JOIN_LINE_HALF_WIDTH_RAD)
        if match is None or not _at_window_edge(match.pose, centre, grid.resolution_m):
            break
        centre = match.pose
    if match is None:
        return predicted
    pose = refine_pose(grid, points, match.pose)
    if match.runner_up_score <= 0.0:
        return pose
    if match.line_direction is None:
        return predicted
    u = match.line_direction
    along = float((predicted[:2] - pose[:2]) @ u)
    return np.array([pose[0] + along * u[0], pose[1] + along * u[1], pose[2]])


def _at_window_edge(pose: np.ndarray, centre: np.ndarray, resolution_m: float) -> bool:
    """Whether a join match ``pose`` lies on the edge of its window around ``centre`` (within a cell or
    an angular step of it): the best pose may lie beyond."""
    moved = pose - centre
    return bool(abs(float(wrap_angle(moved[2]))) >= JOIN_WINDOW_RAD - JOIN_EDGE_RAD
                or max(abs(moved[0]), abs(moved[1])) >= JOIN_WINDOW_M - resolution_m)


def localize_log(bundle: MapBundle, log: DriveLog, config: SlamConfig | None = None, hint: np.ndarray | None = None,
                 threads: int = 1) -> tuple[DriveScans, LocalizationResult]:
    """:func:`localize` of a drive log: its scans (:meth:`DriveScans.from_log`, returned too) and the
    result, whose wall time covers reading and matching the drive's scans. With ``threads`` > 1 the
    drive's scans are matched in a second thread, while this one builds the saved map's index and then
    makes the first try at placing the drive on its first scans (their ``START_STRETCHES`` stretches of
    travel, as soon as they are matched); both spend their time in numba kernels that release the GIL.
    The try's outcome is used as it is unless a stretch it searched ran to the last of those scans (the
    drive beyond might have changed it): the result is the same as with one thread."""
    config = SlamConfig() if config is None else config
    started = time.perf_counter()
    if threads <= 1:
        drive = DriveScans.from_log(log, config)
        index = MapIndex.of_bundle(bundle, config.localization)
        return drive, _placed(index, drive, config, hint, threads, started, MapPlaces.of(bundle, config))
    start_ready = threading.Event()
    start: list[DriveScans] = []

    def on_start(scans: DriveScans) -> None:
        start.append(scans)
        start_ready.set()

    with ThreadPoolExecutor(1) as pool:
        matching = pool.submit(DriveScans.from_log, log, config, on_start,
                               START_STRETCHES * config.localization.stretch_m)
        matching.add_done_callback(lambda _: start_ready.set())  # also when it fails before its start
        index = MapIndex.of_bundle(bundle, config.localization)
        places = MapPlaces.of(bundle, config)
        start_ready.wait()
        tried: dict[int, tuple[int, int, np.ndarray] | None] = {}
        early = None
        if start:
            early = Localizer(index, start[0], config.localization, threads, places=places)
            outcome = early.first_try(0, hint)
            if start[0].reached_end:
                early = None  # the rest of the drive might have changed it: tried again on the whole drive
            else:
                tried[0] = outcome
        drive = matching.result()
    return drive, _placed(index, drive, config, hint, threads, started, places, tried, early)


def localize(bundle: MapBundle, drive: DriveScans, config: SlamConfig | None = None, hint: np.ndarray | None = None,
             threads: int = 1) -> LocalizationResult:
    """Localise ``drive`` in the map of ``bundle`` (see the module docstring); ``hint``: the map pose of
    the drive's first scan, if known."""
    config = SlamConfig() if config is None else config
    started = time.perf_counter()
    return _placed(MapIndex.of_bundle(bundle, config.localization), drive, config, hint, threads, started,
                   MapPlaces.of(bundle, config))


def _placed(index: MapIndex, drive: DriveScans, config: SlamConfig, hint: np.ndarray | None, threads: int,
            started: float, places: MapPlaces | None = None, tried: dict | None = None,
            early: Localizer | None = None) -> LocalizationResult:
    """The drive placed and tracked in the map of ``index`` (``places``: its place index, where stretches
    are searched for first): ``search_s`` that alone took (the localizer's own wall time), ``wall_time_s``
    since ``started`` (``time.perf_counter()``). ``tried``: first tries made before by ``early`` (on the
    drive's first scans), whose searches count too."""
    localizer = Localizer(index, drive, config.localization, threads, OwnLoops.of(config), places)
    if early is not None:
        localizer.best_score, localizer.global_searches = early.best_score, early.global_searches
        localizer.whole_map_searches = early.whole_map_searches
        localizer.failed_tries = dict(early.failed_tries)
    result = localizer.run(hint, tried)
    result.search_s, result.wall_time_s = result.wall_time_s, time.perf_counter() - started
    return result


def refusal_reason(result: LocalizationResult, min_score: float) -> str:
    """Why a drive was not placed, in one line (for a refused drive's message): the best score against
    ``min_score`` and what became of the stretches tried."""
    what = {LOW_SCORE: f"below {min_score:g}", AMBIGUOUS: "ambiguous (another place fit almost as well)",
            NOT_CONFIRMED: "not confirmed by the next stretch", TOO_SHORT: "too near the drive's end to confirm",
            SEEN_THROUGH: "placed where the map saw free space through its returns"}
    text = f"best score {result.best_score:.3f} ({min_score:g} needed, unambiguous and confirmed)"
    tries = sorted(result.failed_tries.items(), key=lambda item: -item[1])
    if not tries:
        return text
    counted = ", ".join(f"{n} {what.get(reason, reason)}" for reason, n in tries)
    total = sum(n for _, n in tries)
    return f"{text}; of {total} {'stretch' if total == 1 else 'stretches'} tried: {counted}"
