"""Loop closing over the front end's key frames: the back end of the SLAM pipeline.

Walks the key frames in time order, as a live system would. Each key frame's pose is predicted
from the last optimised one by the front end's relative motion. Every ``search_every_m`` of travel
the key frame looks for loops: submaps finished at least ``min_loop_travel_m`` of travel ago whose
key frames come within reach of its predicted pose. The reach, in metres and radians, grows with
the travel that separates the two in the graph so far (drift accumulates along the drive; an
accepted closure is a short cut) and is bounded.
Each candidate is verified by a global correlative match of the scan against the submap over that
window (:mod:`slam_engine.backend.correlative`); it is accepted only when

- its score (mean blurred hit value under the scan's end points) reaches ``min_score``,
- it is unique: no other pose farther than ``ambiguity_m`` / ``ambiguity_rad`` scores within
  ``runner_up_ratio`` of it (symmetric corridors, repeated rooms), or the poses that do all lie on
  one line through it at its heading (a corridor seen from inside): then it is a *heading closure*,
  which fixes only the heading (a parallel corridor, which the window may hold instead of the
  true one, fits as well, but at the same heading), and
- when the window was wider than ``confirm_window_m``, the next searching key frame finds a closure
  that implies the same correction (one lucky match never bends the map).

An accepted closure becomes a robust (Cauchy) edge from the submap's anchor to the key frame in the
pose graph (:mod:`slam_engine.backend.pose_graph`), a heading closure one whose position is left
loose (``HEADING_CLOSURE_SD_M``); the graph is optimised when the correction is noticeable, and once
more at the end. Heading closures do not shorten the search windows: the position stays as
uncertain as it was. Drift on long drives is mostly heading drift, so corridors, where most of a
building's loops close, keep it in check even where no pose closure is found.

Where no window reaches any more (``far_search``: most key frames ``far_min_gap_m`` behind are further
from the key frame in the graph than ``max_window_m`` holds, as outdoors, where the drive comes back
after hundreds of metres without a closure), every ``far_every_m`` the stretch of key frames ending
at the key frame is searched for over the whole map behind it (branch and bound, every heading, on
``far_resolution_m`` cells). A placement counts when it is unique and confirmed: the stretch before
it, searched for on its own, or the last far search's placement lands where the front end's motion
puts it. It is then matched against the submap it landed in (no overlap check: the two stretches
placed it over the whole map), and becomes a closure: the windows reach again from there. After a far
closure that moved its key frame farther than ``far_second_pass_m``, :func:`close_loops` goes through
the key frames once more from the corrected poses: the windowed searches before it had started from
estimates too far off to reach the map they overlap. That pass predicts each key frame by the corrected
poses' motion, but its graph and submaps keep the front end's motions, which are locally consistent (the
first pass's result may be bent where its closures pulled).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from slam_engine.backend.correlative import CorrelativeMatch, MatchGrid, angular_step_rad, refine_pose, search
from slam_engine.backend.place_index import PlaceIndex, search_at_places
from slam_engine.backend.pose_graph import Edge, PoseGraph
from slam_engine.backend.submaps import Submap, SubmapGrids, match_grid_from_points, split_into_submaps
from slam_engine.backend.travel_graph import adjacency, shortest_distances
from slam_engine.config import LoopClosingConfig, PlaceIndexConfig
from slam_engine.model.poses import compose, place_each, place_points, relative, wrap_angle

# how much drift an accepted closure leaves between the key frames it joins, in metres of travel
CLOSURE_TRAVEL_M = 1.0
# a key frame needs this many end points over a submap to be matched against it
MIN_OVERLAP_POINTS = 30
# a pose closure that moves its key frame farther than this [m] is checked with the points that overlap
# the submap where it was found (:func:`overlap_score`): the search picked them where it was predicted
OVERLAP_CHECK_M = 2.0
# a verified closure not used because another submap matched the same key frame better
OUTSCORED = "another submap matched better"
# standard deviation of a heading closure's position [m]: the match does not fix it
HEADING_CLOSURE_SD_M = 30.0
# far searches (LoopClosingConfig.far_search): they start once the map far behind holds this many key
# frames and this share of them is beyond every window's reach ...
FAR_MIN_KEY_FRAMES, FAR_OUT_OF_REACH_SHARE = 20, 0.8
FAR_LEVELS = 10  # ... search a grid with a pyramid up to 512 cells (102 m at 0.2 m) ...
FAR_STRETCH_POINTS, FAR_MIN_POINTS = 400, 50  # ... with a stretch's end points, at most / at least ...
PLACE_QUERY_POINTS = 3000  # ... and at most this many describe it to the place index
# ... and a placement is confirmed when the stretch before it lands within this many grid cells and this
# turn [rad] of where the front end's motion puts it
FAR_AGREE_CELLS, FAR_AGREE_RAD = 2.0, 0.1
# ... either over the whole map or, when not unique there, within this of where the first puts it [m], [rad]
FAR_NEAR_WINDOW_M, FAR_NEAR_WINDOW_RAD = 5.0, 0.3
# a confirmed placement is then matched against the submap it landed in; the lowest score there
FAR_VERIFY_MIN_SCORE = 0.4
FAR_ACCEPTED = "accepted (far)"  # a far closure's reason
HEADING_TURN_TOO_FAR = "heading closure turns too far"  # see LoopClosingConfig.heading_closure_max_turn_rad


@dataclass(frozen=True)
class Closure:
    """One loop candidate that was matched: key frame ``node`` against ``submap`` (anchor key frame
    ``anchor``), its score and runner-up score, the search window [m, rad], whether it was accepted
    (and why not), the correction it implied for the key frame's predicted pose [m, rad], and the
    matched pose ``T_anchor_from_node`` (x [m], y [m], theta [rad])."""

    node: int
    submap: int
    anchor: int
    score: float
    runner_up_score: float
    window_m: float
    window_rad: float
    accepted: bool
    reason: str
    correction_m: float
    correction_rad: float
    T_anchor_from_node: tuple[float, float, float]
    line_direction: tuple[float, float] | None = None  # unit, anchor frame: a heading closure's line

    @property
    def kind(self) -> str:
        """"pose" (fixes the whole pose) or "heading" (ambiguous along a line: fixes the heading)."""
        return "pose" if self.line_direction is None else "heading"

    def as_dict(self) -> dict:
        return {"node": self.node, "submap": self.submap, "anchor": self.anchor, "kind": self.kind,
                "score": round(self.score, 4), "runner_up_score": round(self.runner_up_score, 4),
                "window_m": round(self.window_m, 3), "window_rad": round(self.window_rad, 4),
                "accepted": self.accepted, "reason": self.reason, "correction_m": round(self.correction_m, 4),
                "correction_rad": round(self.correction_rad, 5)}


@dataclass
class LoopClosingResult:
    """Optimised key-frame poses (K, 3) and every closure tried."""

    poses: np.ndarray
    closures: list[Closure] = field(default_factory=list)
    optimizations: int = 0
    submaps: int = 0
    unverified_steps: int = 0  # front-end steps not verified by a scan match (loose motion edges)
    edges: list[Edge] = field(default_factory=list)  # the final pose graph's (motions and accepted closures)
    far_search: dict | None = None  # far searches made, placed, confirmed, accepted (None: not enabled)

    def summary(self) -> dict:
        accepted = [c for c in self.closures if c.accepted]
        reasons: dict[str, int] = {}
        for c in self.closures:
            if not c.accepted:
                reasons[c.reason] = reasons.get(c.reason, 0) + 1
        return {"submaps": self.submaps, "unverified_steps": self.unverified_steps,
                "candidates_matched": len(self.closures),
                "closures_accepted": len(accepted),
                "heading_closures_accepted": sum(1 for c in accepted if c.kind == "heading"),
                "closures_rejected": reasons,
                "optimizations": self.optimizations,
                "largest_correction_m": round(max((c.correction_m for c in accepted), default=0.0), 4),
                "far_search": self.far_search,
                "closures": [c.as_dict() for c in self.closures if c.accepted or c.reason != "no match"]}


@dataclass(frozen=True)
class _Found:
    """A verified closure of key frame ``node`` against the submap anchored at ``anchor``: the matched
    ``T_anchor_from_node``, the search half width [m], its index in the closure records and, for a
    heading closure, the unit direction of the line it is ambiguous along (anchor frame)."""

    node: int
    anchor: int
    T_anchor_from_node: np.ndarray
    window_m: float
    record: int
    line_direction: np.ndarray | None = None

    @property
    def kind(self) -> str:
        return "pose" if self.line_direction is None else "heading"

    def world_line(self, est: np.ndarray) -> np.ndarray:
        """The line's unit direction in the world frame, for the anchor at ``est[anchor]``."""
        assert self.line_direction is not None
        theta = float(est[self.anchor, 2])
        cos, sin = math.cos(theta), math.sin(theta)
        u = self.line_direction
        return np.array([cos * u[0] - sin * u[1], sin * u[0] + cos * u[1]])


@dataclass(frozen=True)
class _FarIndex:
    """The map far behind, as far searches take it: the blurred hit grid of key frames ``nodes`` at their
    estimates then (world frame), its centre pose and the half width that covers it [m], the travel it
    reaches up to [m], the estimate's version it was built from and its places (along ``nodes``)."""

    grid: MatchGrid
    nodes: np.ndarray
    centre: np.ndarray
    reach_m: float
    until_m: float
    moved: int
    places: PlaceIndex | None = None


@dataclass(frozen=True)
class _Candidate:
    """A submap to match a key frame against: its match grid, the key frame's predicted pose in its
    frame (``T_anchor_from_node``), the cloud's points that overlap it there and the search half
    widths [m, rad]."""

    submap: Submap
    grid: MatchGrid
    initial: np.ndarray
    points: np.ndarray
    window_m: float
    window_rad: float


def thin(points: np.ndarray, budget: int) -> np.ndarray:
    """Every n-th point (row) so that at most ``budget`` remain."""
    if len(points) > budget:
        return points[:: int(math.ceil(len(points) / budget))]
    return points


def _within_bounds(grid: MatchGrid, xy_m: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each point ``xy_m`` (N, 2) [m, submap frame] lies within the submap's bounds
    (everywhere when it has none)."""
    if grid.bounds_m is None:
        return np.ones(len(xy_m), bool)
    b = grid.bounds_m
    return (xy_m[:, 0] >= b[0]) & (xy_m[:, 0] <= b[2]) & (xy_m[:, 1] >= b[1]) & (xy_m[:, 1] <= b[3])


def overlapping_points(grid: MatchGrid, points_v: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The points of ``points_v`` (N, 2) [m, vehicle frame] that land within the submap's bounds at
    ``pose`` (vehicle in the submap's frame): points beyond them can only score where the scan is
    shifted onto the submap, which favours shifts that overlap more (a corridor seen half by the
    submap would match one door too far)."""
    if grid.bounds_m is None:
        return points_v
    return points_v[_within_bounds(grid, place_points(pose, points_v))]


def overlap_score(grid: MatchGrid, cloud: np.ndarray, pose: np.ndarray, origins: np.ndarray | None = None
                  ) -> float | None:
    """Score of a match at ``pose`` with the points of ``cloud`` (N, 2) [m, vehicle frame] that land on
    the submap there; None (no evidence either way) with fewer than ``MIN_OVERLAP_POINTS`` on cells it
    saw. A search scores the points that overlap the submap at the predicted pose: shifted metres
    along a corridor they may fit, while the points that overlap the submap at the shifted pose do
    not. On infinite-corridor-rough false closures 5-9 m along corridors scored 0.72-0.91 in the
    search and 0.26-0.58 here; true ones 0.6-0.9 in both.

    Points on cells the submap saw score their value (the best pose within a cell and an angular
    step). A point on a cell it never saw is left out (a short-range scanner's submap leaves much of
    its bounds unseen: counted as misses, they cost exp2 nine true closures), unless its ray from
    ``origins`` (N, 2, where each point's scan was taken) crossed one of the submap's walls on its way
    there (a scan that sees through a wall): then it counts as a miss."""
    world = place_points(pose, cloud)
    seen = grid.observed_at(world)
    points = np.ascontiguousarray(cloud[seen])
    if len(points) < MIN_OVERLAP_POINTS:
        return None
    check = search(grid, points, pose, grid.resolution_m, angular_step_rad(points, grid.resolution_m), 0.0)
    score = 0.0 if check is None else check.score
    if origins is None or grid.observed is None:
        return score
    unseen = ~seen & _within_bounds(grid, world)
    through = int(np.count_nonzero(_crosses_a_wall(grid, place_points(pose, origins[unseen]), world[unseen])))
    return score * len(points) / (len(points) + through)


def _overlap_fails(grid: MatchGrid, cloud: np.ndarray, pose: np.ndarray, origins: np.ndarray,
                   min_score: float) -> bool:
    """Whether :func:`overlap_score` is below ``min_score`` (False where it abstains)."""
    score = overlap_score(grid, cloud, pose, origins)
    return score is not None and score < min_score


def _crosses_a_wall(grid: MatchGrid, start_m: np.ndarray, end_m: np.ndarray, clear_m: float = 0.15,
                    wall: float = 0.5) -> np.ndarray:
    """(N,) bool: whether each ray from ``start_m`` to ``end_m`` (N, 2) [m, grid frame] passes a cell
    of ``grid`` worth at least ``wall`` (of 1) more than ``clear_m`` before its end (the blur of the
    wall the point itself may sit on is not crossed)."""
    if len(start_m) == 0:
        return np.zeros(0, bool)
    step = 0.5 * grid.resolution_m
    length = np.hypot(*(end_m - start_m).T)
    n = np.maximum(np.ceil((length - clear_m) / step).astype(np.int64), 0)
    ray = np.repeat(np.arange(len(n)), n)
    t = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) * step / np.maximum(np.repeat(length, n), 1e-9)
    xy = start_m[ray] + t[:, None] * (end_m - start_m)[ray]
    ij = np.floor((xy - grid.origin_m) / grid.resolution_m).astype(np.int64)
    h, w = grid.values.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    hit = np.zeros(len(ray), bool)
    hit[inside] = grid.values[ij[inside, 1], ij[inside, 0]] >= wall * 255
    return np.bincount(ray[hit], minlength=len(n)) > 0


class LoopCloser:
    """Loop closing over key frames with poses ``path`` (K, 3, world frame, from the front end)
    and end points ``points_v`` (K lists of (B, 2) [m], vehicle frame)."""

    def __init__(self, path: np.ndarray, points_v: list[np.ndarray], config: LoopClosingConfig, resolution_m: float,
                 unverified: np.ndarray | None = None, threads: int = 1, guide: np.ndarray | None = None,
                 places: PlaceIndexConfig | None = None):
        self.config = config
        self.places = places  # far searches look only around the places its index proposes (None: everywhere)
        self.threads = max(1, int(threads))
        self.path = np.asarray(path, np.float64)
        # the poses the walk predicts each key frame from (a second pass: the first's corrected poses); the
        # motion edges and the submaps keep the front end's path, which is locally consistent
        self.guide = self.path if guide is None else np.asarray(guide, np.float64)
        if self.guide.shape != self.path.shape:
            raise ValueError(f"guide has shape {self.guide.shape}, the path {self.path.shape}")
        # steps whose motion from the key frame before the front end did not verify by a scan match
        self.unverified = np.zeros(len(self.path), bool) if unverified is None else np.array(unverified, bool)
        if self.unverified.shape != (len(self.path),):
            raise ValueError(f"unverified has shape {self.unverified.shape}, the path {len(self.path)} key frames")
        self.unverified[:1] = False
        c = config
        in_reach = [p[np.hypot(p[:, 0], p[:, 1]) <= c.match_range_m] for p in points_v]
        self.points_v = [thin(p, c.max_points) for p in in_reach]
        self.counts = np.array([len(p) for p in self.points_v], np.int64)
        # unverified with a scan to match: the match was rejected, so the motion may be off by more than
        # its model allows and the windows across it widen (a scan without returns says nothing of the
        # kind: with 10 % of a simulated office's scans blank, widening across those too lost the map)
        self._rejected = self.unverified & np.array([len(p) >= MIN_OVERLAP_POINTS for p in in_reach], bool)
        step = np.hypot(*np.diff(self.path[:, :2], axis=0).T) if len(self.path) > 1 else np.zeros(0)
        self.travel_m = np.concatenate([[0.0], np.cumsum(step)])
        # a submap ends at an unverified key frame: the next one may have gone back to the map (the
        # unverified one alone was off) or on from it, and the next submap is consistent either way
        after_unverified = np.concatenate([[False], self.unverified[:-1]])
        self.submaps = split_into_submaps(self.travel_m, c.submap_length_m, c.submap_max_nodes, after_unverified)
        self.submap_of = np.empty(len(self.path), np.int64)
        for s in self.submaps:
            self.submap_of[s.first: s.last + 1] = s.index
        self._submap_first = np.array([s.first for s in self.submaps], np.int64)
        self._submap_last = np.array([s.last for s in self.submaps], np.int64)
        self.grids = SubmapGrids(self.submaps, self.path, in_reach, resolution_m, margin_m=1.0,
                                 unobserved=c.unobserved_score)
        self.graph = self.motion_graph()
        self._closure_links: list[tuple[int, int]] = []
        # (closures it holds, adjacency) of the drive-distance graph, rebuilt when closures are added
        self._links: tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        self._accepted: list[_Found] = []
        self._moved = 0  # how often the estimate was re-optimised (the far index is stale after it)
        self._far_index: _FarIndex | None = None
        self._last_far_m = -np.inf
        # a far placement awaiting confirmation: (key frame, its world pose, the estimate's version then)
        self._far_pending: tuple[int, np.ndarray, int] | None = None
        self.far_stats = {"searches": 0, "placed": 0, "confirmed": 0, "accepted": 0}
        if places is not None:
            self.far_stats["whole_map"] = 0  # far placements searched for over the whole map: none proposed

    def motion_graph(self) -> PoseGraph:
        """The key frames tied by the front end's motions (loose where a step is unverified)."""
        c = self.config
        graph = PoseGraph(self.path, cauchy_scale=c.cauchy_scale)
        for k in range(1, len(self.path)):
            motion = relative(self.path[k - 1], self.path[k])
            sigmas = self._motion_sigmas(motion)
            if self.unverified[k]:
                sigmas = np.maximum(sigmas, [c.unverified_sd_m, c.unverified_sd_m, c.unverified_sd_rad])
            graph.add_edge(k - 1, k, motion, sigmas)
        return graph

    def _motion_sigmas(self, motion: np.ndarray) -> np.ndarray:
        c = self.config
        d = float(np.hypot(motion[0], motion[1]))
        sd_xy = c.motion_sd_m + c.motion_sd_per_m * d
        sd_th = c.motion_sd_rad + c.motion_sd_rad_per_rad * abs(float(motion[2])) + c.motion_sd_rad_per_m * d
        return np.array([sd_xy, sd_xy, sd_th])

    def run(self, progress: Callable[[float], None] | None = None) -> LoopClosingResult:
        """Search every key frame for loops, in time order, and optimise the graph; ``progress`` as in
        :func:`close_loops`."""
        c = self.config
        n = len(self.path)
        est = self.guide.copy()
        closures: list[Closure] = []
        optimizations = 0
        last_search_m = -np.inf
        # per kind ("pose", "heading"), a closure awaiting an agreeing second one of the same kind (a
        # heading closure cannot vouch for a pose closure)
        pending: dict[str, _Found] = {}
        for k in range(1, n):
            if progress is not None:
                progress((k - 1) / n)
            est[k] = compose(est[k - 1], relative(self.guide[k - 1], self.guide[k]))
            if self.travel_m[k] - last_search_m < c.search_every_m or not len(self.points_v[k]):
                continue
            last_search_m = self.travel_m[k]
            travel_to = self._uncertain_travel(k)
            found = self._search_node(k, est, travel_to, closures)
            if found is None:
                far = self._far_search(k, est, closures) if c.far_search and self._far_due(k, travel_to) else None
                if far is not None:  # already confirmed by a second stretch
                    self._add_closure(far)
                    est[: k + 1] = self.graph.optimize(est, nodes=k + 1, robust=False)
                    optimizations += 1
                    self._moved += 1
                continue
            kind = found.kind
            if found.window_m > c.confirm_window_m:
                waiting = pending.pop(kind, None)
                if waiting is None or not self._agrees(waiting, found, est):
                    if waiting is not None:
                        closures[waiting.record] = replace(closures[waiting.record], reason="not confirmed")
                    pending[kind] = found
                    closures[found.record] = replace(closures[found.record], accepted=False,
                                                     reason="awaiting confirmation")
                    continue
                self._add_closure(waiting)
                closures[waiting.record] = replace(closures[waiting.record], accepted=True,
                                                   reason="accepted (confirmed)")
            else:
                superseded = pending.pop(kind, None)  # the window has narrowed since
                if superseded is not None:
                    closures[superseded.record] = replace(closures[superseded.record], reason="not confirmed")
            self._add_closure(found)
            offset_m, offset_rad = self._offset(found, est)
            if offset_m > c.reoptimize_m or offset_rad > c.reoptimize_rad:
                est[: k + 1] = self.graph.optimize(est, nodes=k + 1, robust=False)
                optimizations += 1
                self._moved += 1
        for waiting in pending.values():
            closures[waiting.record] = replace(closures[waiting.record], reason="not confirmed")
        if any(cl.accepted for cl in closures):
            # the final graph ties each closure to the key frame of its submap nearest to the node, so
            # that the front end's drift within a submap bends too; least squares first (every verified
            # closure pulls), then the robust losses from there: a closure that disagrees with the rest
            # is then an outlier and lets go
            self.graph = self.motion_graph()
            for found in self._accepted:
                self._add_closure_edge(self.graph, found, to_nearest=True)
            est = self.graph.optimize(self.graph.optimize(est, robust=False))
            optimizations += 2
        return LoopClosingResult(poses=est, closures=closures, optimizations=optimizations, submaps=len(self.submaps),
                                 unverified_steps=int(self.unverified.sum()), edges=list(self.graph.edges),
                                 far_search=dict(self.far_stats) if c.far_search else None)

    # --- far closures: where no window reaches -------------------------------------------------
    def _far_due(self, k: int, travel_to: np.ndarray) -> bool:
        """Whether key frame k searches the map far behind it over the whole map: ``far_every_m`` after
        the last far search, with most key frames at least ``far_min_gap_m`` behind out of every window's
        reach (``travel_to``: :meth:`_uncertain_travel`, inf beyond what ``max_window_m`` holds)."""
        c = self.config
        if self.travel_m[k] - self._last_far_m < c.far_every_m:
            return False
        behind = travel_to[: k][self.travel_m[: k] < self.travel_m[k] - c.far_min_gap_m]
        return len(behind) >= FAR_MIN_KEY_FRAMES and float(np.mean(np.isinf(behind))) >= FAR_OUT_OF_REACH_SHARE

    def _far_search(self, k: int, est: np.ndarray, closures: list[Closure]) -> _Found | None:
        """Key frame k placed in the map far behind it: the stretch of key frames ending at k and the one
        before it, each searched for over the whole map behind them (branch and bound, every heading),
        unique, scoring ``far_min_score`` and agreeing through the front end's motion between them; then
        matched against the submap it landed in (:meth:`_far_verified`). The closure, or None."""
        self._last_far_m = float(self.travel_m[k])
        first_a = self._stretch_start(k)
        if first_a is None or first_a < 1:
            return None
        j = first_a - 1
        first_b = self._stretch_start(j)
        if first_b is None:
            return None
        index = self._far_index_for(first_b, est)
        if index is None:
            return None
        self.far_stats["searches"] += 1
        placed_a = self._far_place(index, first_a, k)
        if placed_a is None:
            return None
        self.far_stats["placed"] += 1
        # confirmed by the last far search's placement, when it awaits one and the estimate has not moved
        # since, or else by the stretch before this one, searched for on its own
        pending, self._far_pending = self._far_pending, None
        confirmed = pending is not None and pending[2] == self._moved and self._far_agree(pending[0], pending[1], k,
                                                                                           placed_a)
        if not confirmed:
            placed_b = self._far_place(index, first_b, j)
            if placed_b is None:  # not unique over the whole map: then unique near where the first puts it
                placed_b = self._far_place(index, first_b, j,
                                           near=compose(placed_a, relative(self.path[k], self.path[j])))
            confirmed = placed_b is not None and self._far_agree(j, placed_b, k, placed_a)
        if not confirmed:
            self._far_pending = (k, placed_a, self._moved)
            return None
        self.far_stats["confirmed"] += 1
        # verified as a windowed closure would be, against the submap of the key frame nearest to it
        nearest = index.nodes[int(np.argmin(np.hypot(*(est[index.nodes, :2] - placed_a[:2]).T)))]
        found = self._far_verified(k, self.submaps[self.submap_of[nearest]], placed_a, est, index.reach_m, closures)
        self.far_stats["accepted"] += found is not None
        return found

    def _far_verified(self, k: int, s: Submap, placed: np.ndarray, est: np.ndarray, reach_m: float,
                      closures: list[Closure]) -> _Found | None:
        """A far placement of key frame k (world pose ``placed``) matched against submap ``s`` within the
        far search's tolerance, scoring ``FAR_VERIFY_MIN_SCORE`` and unique there: the closure, or None.
        No overlap check: two stretches placed it over the whole map (outdoors, where trees and cars
        change between passes, the check refused placements 7 cm from the truth)."""
        c = self.config
        grid = self.grids.grid(s.index)
        if grid is None:
            return None
        initial = relative(est[s.anchor], placed)
        cloud = self.match_points(k)
        points = overlapping_points(grid, cloud, initial)
        if len(points) < MIN_OVERLAP_POINTS:
            return None
        result = self._match(k, _Candidate(s, grid, initial, points, FAR_AGREE_CELLS * c.far_resolution_m,
                                           FAR_AGREE_RAD), min_score=FAR_VERIFY_MIN_SCORE)
        if result is None:
            return None
        match, pose = result
        delta = relative(relative(est[s.anchor], est[k]), pose)
        correction_m = float(np.hypot(delta[0], delta[1]))
        reason = "far: ambiguous in its submap" if match.runner_up_score >= c.runner_up_ratio * match.score \
            else FAR_ACCEPTED
        closures.append(Closure(k, s.index, s.anchor, match.score, match.runner_up_score, reach_m, math.pi,
                                reason == FAR_ACCEPTED, reason, correction_m, float(abs(delta[2])),
                                (float(pose[0]), float(pose[1]), float(pose[2]))))
        return _Found(k, s.anchor, pose, reach_m, len(closures) - 1) if closures[-1].accepted else None

    def _far_agree(self, i: int, pose_i: np.ndarray, k: int, pose_k: np.ndarray) -> bool:
        """Whether world poses found for key frames i and k agree through the front end's motion between
        them (within ``FAR_AGREE_CELLS`` far cells and ``FAR_AGREE_RAD``)."""
        via_i = compose(pose_i, relative(self.path[i], self.path[k]))
        return bool(math.hypot(*(via_i[:2] - pose_k[:2])) <= FAR_AGREE_CELLS * self.config.far_resolution_m
                    and abs(float(wrap_angle(via_i[2] - pose_k[2]))) <= FAR_AGREE_RAD)

    def _stretch_start(self, last: int) -> int | None:
        """The first key frame of the stretch of ``far_stretch_m`` of travel that ends at ``last`` (None
        when the drive is not that long yet)."""
        start_m = self.travel_m[last] - self.config.far_stretch_m
        if start_m < 0:
            return None
        return min(int(np.searchsorted(self.travel_m, start_m, side="right")), last)

    def _stretch_cloud(self, first: int, last: int) -> np.ndarray:
        """The end points of key frames ``first..last`` in ``last``'s vehicle frame, by the front end's
        relative poses, thinned to ``FAR_STRETCH_POINTS``."""
        return np.ascontiguousarray(self._frames_cloud(np.arange(first, last + 1), last, FAR_STRETCH_POINTS)[0])

    def _far_place(self, index: _FarIndex, first: int, last: int, near: np.ndarray | None = None) -> np.ndarray | None:
        """Key frame ``last``'s world pose from its stretch searched for over the whole far index (its best
        pose only around the places the index proposes, when it has places): None unless it scores
        ``far_min_score`` and nothing farther than the ambiguity distance scores nearly as well."""
        c = self.config
        cloud = self._stretch_cloud(first, last)
        if len(cloud) < FAR_MIN_POINTS:
            return None
        initial, window_m, window_rad = (index.centre, index.reach_m, math.pi) if near is None else \
            (near, FAR_NEAR_WINDOW_M, FAR_NEAR_WINDOW_RAD)
        proposed = []
        if near is None and index.places is not None and self.places is not None:
            described = self._frames_cloud(np.arange(first, last + 1), last, PLACE_QUERY_POINTS)[0]
            proposed = index.places.query(described, self.places.candidates)
            self.far_stats["whole_map"] += not proposed
        if proposed:
            assert self.places is not None
            match = search_at_places(index.grid, cloud, initial, window_m, window_rad, proposed, self.places.window_m,
                                     self.places.window_rad, c.far_min_score, c.ambiguity_m, c.ambiguity_rad,
                                     c.runner_up_ratio, c.runner_up_ratio * c.far_min_score, threads=self.threads)
        else:
            match = search(index.grid, cloud, initial, window_m, window_rad, c.far_min_score,
                           ambiguity_m=c.ambiguity_m, ambiguity_rad=c.ambiguity_rad, runner_up_share=c.runner_up_ratio,
                           runner_up_min_score=c.runner_up_ratio * c.far_min_score, threads=self.threads,
                           any_runner_up=True)
        if match is None or match.runner_up_score >= c.runner_up_ratio * match.score:
            return None
        return match.pose

    def _far_index_for(self, first: int, est: np.ndarray) -> _FarIndex | None:
        """The whole-map grid of the key frames at least ``far_min_gap_m`` of travel before key frame
        ``first``, at their current estimates; kept while the estimate has not moved and it lacks less
        than ``far_rebuild_m`` of that travel."""
        c = self.config
        until_m = self.travel_m[first] - c.far_min_gap_m
        cached = self._far_index
        if (cached is not None and cached.moved == self._moved and cached.until_m <= until_m
                and until_m - cached.until_m < c.far_rebuild_m):
            return cached
        nodes = np.flatnonzero(self.travel_m[:first] < until_m)
        nodes = nodes[self.counts[nodes] > 0]
        if len(nodes) < FAR_MIN_KEY_FRAMES:
            return None
        counts = self.counts[nodes]
        world = place_each(est[nodes], np.concatenate([self.points_v[n] for n in nodes.tolist()]),
                           np.repeat(np.arange(len(nodes)), counts))
        grid = match_grid_from_points(world, c.far_resolution_m, 1.0, n_levels=FAR_LEVELS)
        places = None if self.places is None else \
            PlaceIndex.along(world, est[nodes, :2], self.places.spacing_m, self.places.radius_m)
        self._far_index = _FarIndex(grid, nodes, *grid.centre_and_reach(), until_m, self._moved, places)
        return self._far_index

    def _candidates(self, k: int, est: np.ndarray, window_m: float) -> list[tuple[int, float]]:
        """Finished submaps, far enough back along the drive, with a key frame within reach of k:
        (index, distance from k to its nearest key frame [m]), nearest first."""
        c = self.config
        first, last = self._submap_first, self._submap_last
        done = (last < k) & ~(self.travel_m[k] - self.travel_m[last] < c.min_loop_travel_m)
        if not done.any():
            return []
        # the submaps partition the key frames in order: each one's nearest node in one pass
        started = first < k
        dist = np.minimum.reduceat(np.hypot(*(est[:k, :2] - est[k, :2]).T), first[started])
        index = np.flatnonzero(started)
        near = done[started] & (dist <= window_m + c.overlap_m)
        out = sorted(zip(dist[near].tolist(), index[near].tolist(), strict=True))
        return [(s_index, d) for d, s_index in out[: c.candidates_per_search]]

    def _uncertain_travel(self, k: int) -> np.ndarray:
        """(K,) how much drive separates key frame k from every other in the graph so far [m]: the
        shortest path over front-end motions (their travel) and accepted closures (each worth
        ``CLOSURE_TRAVEL_M``). Drift, and so the search window, grows with it."""
        if self._links is None or self._links[0] != len(self._closure_links):
            n = len(self.path)
            step = np.maximum(np.diff(self.travel_m), 1e-3) + self.config.unverified_travel_m * self._rejected[1:]
            start = np.concatenate([np.arange(n - 1), np.array([i for i, _ in self._closure_links], np.int64)])
            end = np.concatenate([np.arange(1, n), np.array([j for _, j in self._closure_links], np.int64)])
            length = np.concatenate([step, np.full(len(self._closure_links), CLOSURE_TRAVEL_M)])
            self._links = (len(self._closure_links), adjacency(n, start, end, length))
        c = self.config
        limit = (c.max_window_m - c.base_window_m) / max(c.window_per_m, 1e-9)
        return shortest_distances(*self._links[1], k, limit)

    def _search_node(self, k: int, est: np.ndarray, travel_to: np.ndarray, closures: list[Closure]
                     ) -> _Found | None:
        """Match key frame k against its candidate submaps (``travel_to``: :meth:`_uncertain_travel`);
        the best verified one (a pose closure before a heading closure), or None. Each candidate's
        search runs in ``threads`` threads (the result does not depend on it)."""
        c = self.config
        best: tuple[tuple[bool, float], _Found] | None = None
        first_record = len(closures)
        cloud, origins = self.match_cloud(k)
        tasks = []
        for s_index, dist_m in self._candidates(k, est, c.max_window_m):
            s = self.submaps[s_index]
            travel = float(np.min(travel_to[s.first: s.last + 1]))
            window_m = min(c.base_window_m + c.window_per_m * travel, c.max_window_m)
            window_rad = min(c.base_window_rad + c.window_rad_per_m * travel, c.max_window_rad)
            if dist_m > window_m + c.overlap_m:
                continue
            grid = self.grids.grid(s_index)
            if grid is None:
                continue
            initial = relative(est[s.anchor], est[k])
            points = overlapping_points(grid, cloud, initial)
            if len(points) < MIN_OVERLAP_POINTS:
                continue
            tasks.append(_Candidate(s, grid, initial, points, window_m, window_rad))
        for task in tasks:
            result = self._match(k, task)
            if result is None:
                continue
            match, pose = result
            s, grid, initial = task.submap, task.grid, task.initial
            window_m, window_rad = task.window_m, task.window_rad
            ambiguous = match.runner_up_score >= c.runner_up_ratio * match.score
            line = match.line_direction if ambiguous else None
            delta = relative(initial, pose)
            shift = match.pose - initial
            if line is not None:  # only the offset across the line is found (and only the heading is used)
                shift_m = abs(float(line[0] * shift[1] - line[1] * shift[0]))
                correction_m = 0.0
            else:
                shift_m = float(max(abs(shift[0]), abs(shift[1])))
                correction_m = float(np.hypot(delta[0], delta[1]))
            reason = "accepted" if line is None else "accepted (heading)"
            if shift_m > c.edge_share * window_m or abs(float(wrap_angle(shift[2]))) > c.edge_share * window_rad:
                reason = "at the window's edge"
            elif ambiguous and line is None:
                reason = "ambiguous"
            # checked last (a search of its own); a heading closure (correction 0) is not: its position
            # along its line is arbitrary
            elif correction_m > OVERLAP_CHECK_M and _overlap_fails(grid, cloud, pose, origins, c.overlap_min_score):
                reason = "fails with the points it overlaps"
            ok = reason.startswith("accepted")
            closures.append(Closure(k, s.index, s.anchor, match.score, match.runner_up_score, window_m, window_rad,
                                    ok, reason, correction_m, float(abs(delta[2])),
                                    (float(pose[0]), float(pose[1]), float(pose[2])),
                                    None if line is None else (float(line[0]), float(line[1]))))
            rank = (line is None, match.score)
            if ok and (best is None or rank > best[0]):
                best = (rank, _Found(k, s.anchor, pose, window_m, len(closures) - 1, line))
        for i in range(first_record, len(closures)):  # only the best verified candidate is used
            if closures[i].accepted and (best is None or i != best[1].record):
                closures[i] = replace(closures[i], accepted=False, reason=OUTSCORED)
        found = None if best is None else best[1]
        if found is not None and found.line_direction is not None \
                and closures[found.record].correction_rad > c.heading_closure_max_turn_rad:
            # a line alone, turned that far: as likely another straight wall (campus seed 4: two such
            # closures 1.4 rad off the truth turned their key frames 0.25 rad)
            closures[found.record] = replace(closures[found.record], accepted=False, reason=HEADING_TURN_TOO_FAR)
            return None
        return found

    def _match(self, k: int, task: _Candidate, min_score: float | None = None
               ) -> tuple[CorrelativeMatch, np.ndarray] | None:
        """The global match of key frame k's cloud against one candidate submap and its pose refined
        with the key frame's own scan (the older scans in the cloud carry the front end's relative
        error: freiburg-079 0.0196 m instead of 0.0206), or None. ``min_score``: instead of the
        config's (the runner-up too)."""
        c = self.config
        # a window wider than confirm_window_m needs min_score_wide: the search prunes with it (on
        # infinite-corridor-rough 40 % faster than pruning with min_score and rejecting after), while
        # the runner-up still counts from min_score
        wide = task.window_m > c.confirm_window_m
        floor = c.min_score if min_score is None else min_score
        match = search(task.grid, task.points, task.initial, task.window_m, task.window_rad,
                       max(floor, c.min_score_wide) if wide else floor, runner_up_min_score=floor,
                       ambiguity_m=c.ambiguity_m, ambiguity_rad=c.ambiguity_rad, runner_up_share=c.runner_up_ratio,
                       line_half_width_m=c.line_half_width_m if c.heading_closures else 0.0,
                       line_half_width_rad=c.line_half_width_rad, threads=self.threads)
        if match is None:
            return None
        own = overlapping_points(task.grid, self.points_v[k], match.pose)
        return match, refine_pose(task.grid, own if len(own) >= MIN_OVERLAP_POINTS else task.points, match.pose)

    def match_points(self, k: int) -> np.ndarray:
        """What key frame k is matched with (its vehicle frame [m]): its end points and those of the
        key frames over the last ``match_span_m`` of travel before it, placed by the front end's motion
        (locally good to centimetres), thinned to ``max_points``. Metres of corridor hold the doors and
        junctions that tell one stretch from another where a single scan often does not: with a 4 m
        span, infinite-corridor-rough closed its loops on all ten seeds (0.044-0.053 m), where single
        scans accepted false closures 4-9 m along the corridor on four (0.19-1.5 m)."""
        return self.match_cloud(k)[0]

    def match_cloud(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`match_points` and, for each point, where its scan was taken ((N, 2), same frame)."""
        c = self.config
        first = int(np.searchsorted(self.travel_m, self.travel_m[k] - c.match_span_m, side="left"))
        if first >= k:
            return self.points_v[k], np.zeros_like(self.points_v[k])
        return self._frames_cloud(np.arange(k, first - 1, -1), k, c.max_points)  # k first, then back along the drive

    def _frames_cloud(self, frames: np.ndarray, k: int, budget: int) -> tuple[np.ndarray, np.ndarray]:
        """The end points of key frames ``frames`` (in that order) in key frame k's vehicle frame, by the
        front end's relative poses, thinned to ``budget``, and where each point's scan was taken."""
        counts = self.counts[frames]
        owner = thin(np.repeat(np.arange(len(frames)), counts), budget)
        rows = thin(np.arange(int(counts.sum())), budget)
        T = relative(self.path[k], self.path[frames])  # each key frame in k's frame
        points = np.concatenate([self.points_v[j] for j in frames.tolist()])[rows]
        return place_each(T, points, owner), np.ascontiguousarray(T[owner, :2])

    def _agrees(self, first: _Found, second: _Found, est: np.ndarray) -> bool:
        """Whether two closures imply the same correction: the second key frame's pose from the first
        closure and the front end's motion agrees with its pose from the second closure (which came
        within ``confirm_travel_m``). Two heading closures agree when their lines are parallel (within
        10 deg) and the heading and the offset across them agree."""
        c = self.config
        if self.travel_m[second.node] - self.travel_m[first.node] > c.confirm_travel_m:
            return False
        via_first = compose(compose(est[first.anchor], first.T_anchor_from_node),
                            relative(self.path[first.node], self.path[second.node]))
        via_second = compose(est[second.anchor], second.T_anchor_from_node)
        if abs(float(wrap_angle(via_first[2] - via_second[2]))) > c.confirm_rad:
            return False
        gap = via_first[:2] - via_second[:2]
        if first.line_direction is None or second.line_direction is None:
            return bool(np.hypot(gap[0], gap[1]) <= c.confirm_m)
        u, v = first.world_line(est), second.world_line(est)
        return bool(abs(float(u @ v)) >= math.cos(math.radians(10.0))
                    and abs(float(u[0] * gap[1] - u[1] * gap[0])) <= c.confirm_m)

    @staticmethod
    def _offset(found: _Found, est: np.ndarray) -> tuple[float, float]:
        """How far the closure moves its key frame from the estimate ``est`` [m] (0 for a heading
        closure) and turns it [rad]."""
        target = compose(est[found.anchor], found.T_anchor_from_node)
        turn = abs(float(wrap_angle(target[2] - est[found.node, 2])))
        if found.line_direction is not None:
            return 0.0, turn
        return float(np.hypot(*(target[:2] - est[found.node, :2]))), turn

    def _add_closure(self, found: _Found) -> None:
        self._accepted.append(found)
        if found.line_direction is None:
            self._closure_links.append((found.anchor, found.node))
        self._add_closure_edge(self.graph, found, to_nearest=False)

    def _add_closure_edge(self, graph: PoseGraph, found: _Found, to_nearest: bool) -> None:
        """The closure's edge, from its submap's anchor (the submap moves as one rigid piece: while
        searching, so that the estimate the next searches start from stays steady) or ``to_nearest``,
        from the submap's key frame nearest to where the closure puts the node, through the front end's
        motion within the submap (the final graph: the submap's own drift then bends as well; intel
        0.0257 / 0.0283 -> 0.0249 / 0.0266 m replayed, the corridor unchanged; tied so while
        searching, the corridor lost 2 seeds of 10)."""
        c = self.config
        source, T_source_from_node = found.anchor, found.T_anchor_from_node
        if to_nearest:
            s = self.submaps[self.submap_of[found.anchor]]
            in_anchor = relative(self.path[s.anchor], self.path[s.first: s.last + 1])
            nearest = int(np.argmin(np.hypot(*(in_anchor[:, :2] - found.T_anchor_from_node[:2]).T)))
            source, T_source_from_node = s.first + nearest, relative(in_anchor[nearest], found.T_anchor_from_node)
        sd_m = HEADING_CLOSURE_SD_M if found.line_direction is not None else c.closure_sd_m
        graph.add_edge(source, found.node, T_source_from_node, np.array([sd_m, sd_m, c.closure_sd_rad]), robust=True)


def close_loops(path: np.ndarray, points_v: list[np.ndarray], config: LoopClosingConfig, resolution_m: float,
                unverified: np.ndarray | None = None, threads: int = 1,
                progress: Callable[[float], None] | None = None,
                places: PlaceIndexConfig | None = None) -> LoopClosingResult:
    """Optimised key-frame poses for the front end's ``path`` (K, 3) and key-frame end points;
    ``unverified`` (K,) bool marks the steps whose motion the front end did not verify by a scan match.
    Each global search runs in ``threads`` threads (same result for any: :func:`correlative.branch_and_bound`).
    ``progress`` hears the share of key frames searched (0..1) after each one (an exception raised there
    stops the search).

    When a far closure moved its key frame farther than ``far_second_pass_m``, the windowed searches
    before it ran from estimates too far off to reach the map they overlap: the key frames are searched
    once more, each predicted from the one before by the corrected poses' motion, while the graph and the
    submaps keep the front end's motions (``progress`` then hears 1.0). ``places``: the place index's
    settings, when far searches use it (:func:`~slam_engine.backend.place_index.search_at_places`)."""
    if not config.enabled or len(path) < 3:
        return LoopClosingResult(poses=np.asarray(path, np.float64).copy())
    first = LoopCloser(path, points_v, config, resolution_m, unverified, threads, places=places).run(progress)
    if not any(c.reason == FAR_ACCEPTED and c.correction_m > config.far_second_pass_m for c in first.closures):
        return first
    second = LoopCloser(path, points_v, config, resolution_m, unverified, threads, guide=first.poses,
                        places=places).run(
        None if progress is None else lambda _done: progress(1.0))
    second.far_search = {**(first.far_search or {}), "second_pass": second.far_search}
    return second
