"""Localising a drive while it drives: each scan placed in a saved map as it arrives.

The same search and tracking as a whole drive's localisation (:mod:`~slam_engine.multisession.localization`),
taken scan by scan. Each scan is matched to the drive's recent scans (:class:`ScanJoiner`), then:

- **searching** (not placed yet, or lost): the drive is searched for over the whole map (around the places
  the map's place index proposes first, as a whole drive's stretches are) in a background
  thread, on the drive's scans so far (since its last match, when lost): a stretch of ``live_stretch_m`` of
  travel, placed unambiguously and confirmed by the next stretch (grown while ambiguous, as far as the
  drive goes). The scans meanwhile are reported without a pose (or,
  when lost, where the drive's own motion carries it, with confidence 0). A placement is tracked forward
  to the newest scan in that thread, so the scans keep their pace;
- **found**: the scan matched the map near where its motion put it (the tracking of a whole drive);
- **carried**: it did not match, though the map could judge it: placed by the drive's own motion, not
  confidently; after ``live_lost_after_m`` of such travel the drive is **lost** and searched for again
  (carried by its motion meanwhile, confidence 0): a robot carried off (kidnapped) is noticed there, and
  its poses are never reported as found meanwhile. A scan whose score drops sharply below the last found
  scan's is carried too, until a scan scores near that level again (the first scans after a kidnap can
  still fit, weakly, near where the robot was), and so is one while the returns of the scans matched over
  the last 2 m fall where the map saw free space (a look-alike place: its walls fit, its furniture and
  doors do not). A lost drive is found again by a search, whose placement the map's free space must not
  contradict either (``max_seen_through``);
- **outside**: the scan falls where the map never saw: carried by the drive's own motion, not lost.

Poses are those of the moment (no smoothing with later scans: a finished drive's batch localisation
smooths them). Frames: poses ``[x_m, y_m, theta_rad]`` in the saved map's frame; scan end points (N, 2)
[m] in the vehicle frame.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.poses import compose, relative
from slam_engine.multisession.localization import (
    DriveScans,
    Localizer,
    MapIndex,
    MapPlaces,
    ScanJoiner,
    TrackCheck,
)

SEARCHING, FOUND, CARRIED, OUTSIDE, LOST = "searching", "found", "carried", "outside", "lost"
STATES = (SEARCHING, FOUND, CARRIED, OUTSIDE, LOST)


@dataclass(frozen=True)
class LivePose:
    """Where scan ``scan`` (stamped ``t_s``) is: ``pose`` in the map frame (None while searching, never
    placed), its match score ``confidence`` (0-1; 0 unless found) and the ``state`` (module docstring)."""

    scan: int
    t_s: float
    pose: np.ndarray | None
    confidence: float
    state: str

    def as_dict(self) -> dict:
        pose = None if self.pose is None else [round(float(v), 5) for v in self.pose]
        return {"scan": self.scan, "t_s": round(self.t_s, 6), "pose": pose,
                "confidence": round(self.confidence, 4), "state": self.state}


class LiveLocalizer:
    """A drive localised in the map of ``bundle`` scan by scan (:meth:`add`); see the module docstring.
    ``index``: the map's index when already built (it is the slow part of starting)."""

    def __init__(self, bundle: MapBundle, config: SlamConfig | None = None, threads: int = 1,
                 index: MapIndex | None = None):
        self.config = SlamConfig() if config is None else config
        c = self.config.localization
        self.index = index if index is not None else MapIndex.of_bundle(bundle, c)
        self.places = MapPlaces.of(bundle, self.config)  # where searches look first (None: the whole map)
        self.threads = max(1, int(threads))
        self._searching = c.model_copy(update={"stretch_m": c.live_stretch_m})  # the searches' settings
        self.joiner = ScanJoiner(c.local_map_resolution_m, c.local_map_m)
        self.t_s: list[float] = []
        self.hits: list[np.ndarray] = []
        self.own: list[np.ndarray] = []  # the drive's own (scan-matched) poses
        self.travel: list[float] = []
        self.poses: list[np.ndarray | None] = []  # map poses (None: never placed)
        self.reports: list[LivePose] = []
        self.events: list[dict] = []
        self.state = SEARCHING
        self.global_searches = 0
        self.failed_tries: dict[str, int] = {}  # why searches found nothing: how many
        self.best_score = 0.0
        self._tracker = Localizer(self.index, DriveScans(np.zeros(1), np.zeros((1, 3)), self.hits), c)
        self._last_tracked = -1
        self._unmatched_m = 0.0  # travel since the last match over scans the map could judge [m]
        self._next_try_m = 0.0  # the travel at which the next search may start [m]
        self._search: Future | None = None
        self._search_from = 0  # the first scan the next search may start a stretch at
        self._check = TrackCheck(self.index, c)  # whether a matched scan is found
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="live-localization")
        self._lock = threading.Lock()

    # --- scans in ---------------------------------------------------------------------------------
    def add(self, t_s: float, odometry_pose: np.ndarray, hits_v: np.ndarray) -> LivePose:
        """The next scan (stamp [s], its odometry pose in the odometry's frame, its returns (N, 2) [m,
        vehicle frame]) placed; returns its report."""
        hits_v = np.asarray(hits_v, np.float64).reshape(-1, 2)
        self._take_search()
        own = self.joiner.add(odometry_pose, hits_v)
        k = len(self.t_s)
        self.t_s.append(float(t_s))
        self.hits.append(hits_v)
        self.own.append(own)
        self.travel.append(self.joiner.travel_m)
        self.poses.append(None)
        if self.state in (FOUND, CARRIED, OUTSIDE, LOST) and self.poses[k - 1] is not None:
            report = self._track(k)
        else:
            report = LivePose(k, float(t_s), None, 0.0, SEARCHING)
        self.reports.append(report)
        self._maybe_search()
        return report

    def close(self) -> None:
        """Stop the background search (its outcome is dropped)."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def wait(self) -> LivePose | None:
        """Wait for a running search and take its outcome (a stream that has ended; tests). When it placed
        the drive, the newest scan is reported again where the placement puts it (its map pose, state and
        confidence now): that report replaces the scan's first in :attr:`reports` (and in :meth:`summary`)
        and is returned; None otherwise. A placement otherwise lands only with the next scan."""
        if self._search is None:
            return None
        self._search.result()
        report = self._take_search()
        if report is not None:
            self.reports[report.scan] = report
        return report

    # --- tracking ---------------------------------------------------------------------------------
    def _track(self, k: int) -> LivePose:
        """Scan k from scan k - 1's map pose and the drive's motion (:meth:`Localizer.track`)."""
        c = self.config.localization
        previous = self.poses[k - 1]
        assert previous is not None
        predicted = compose(previous, relative(self.own[k - 1], self.own[k]))
        untracked_m = 0.0 if self._last_tracked < 0 else self.travel[k - 1] - self.travel[self._last_tracked]
        if self.state == LOST:  # carried until searches place it again: near where it was carried, a
            # look-alike room of the building would match as well as the right one (a robot carried off)
            self.poses[k] = predicted
            return LivePose(k, self.t_s[k], predicted.copy(), 0.0, LOST)
        pose, score = self._tracker.track(k, predicted, untracked_m)
        uncovered = math.isnan(score)
        moved = pose - predicted
        hits, step_m = self.hits[k], self.travel[k] - self.travel[k - 1]
        if untracked_m > c.live_lost_after_m:  # back from afar: a match is a placement, scored as one
            ok = not uncovered and score >= c.min_score and self._check.accepts_placement(score, pose, hits, step_m)
        else:
            nudged = math.hypot(moved[0], moved[1]) <= c.nudge_m and abs(float(moved[2])) <= c.nudge_rad
            ok = not uncovered and (score >= c.track_min_score or (score >= c.nudge_min_score and nudged))
            ok = ok and self._check.accepts(score, pose, hits, step_m)
        if ok:
            self.poses[k], self._last_tracked, self._unmatched_m = pose, k, 0.0
            self.state = FOUND
            return LivePose(k, self.t_s[k], pose.copy(), float(score), FOUND)
        self.poses[k] = predicted
        if not uncovered:
            self._unmatched_m += self.travel[k] - self.travel[k - 1]
        if self._unmatched_m > c.live_lost_after_m:
            self.state = LOST
            self._event("lost", k)
            self._next_try_m = self.travel[k]
            self._search_from = self._last_tracked + 1  # carried off after its last match, if at all
            self._check.reset(None)
        else:
            self.state = OUTSIDE if uncovered else CARRIED
        return LivePose(k, self.t_s[k], predicted.copy(), 0.0, self.state)

    # --- searching --------------------------------------------------------------------------------
    def _maybe_search(self) -> None:
        """Start a search in the background when the drive is searching or lost, none runs, and it went
        ``live_stretch_m`` since the last one began."""
        c = self.config.localization
        k = len(self.t_s) - 1
        if self.state not in (SEARCHING, LOST) or self._search is not None or self.travel[k] < self._next_try_m:
            return
        self._next_try_m = self.travel[k] + c.live_stretch_m
        drive = DriveScans(np.array(self.t_s), np.array(self.own), list(self.hits))
        self._search = self._pool.submit(self._placed, drive, self._search_from)

    def _placed(self, drive: DriveScans, first_allowed: int) -> tuple[int, np.ndarray, float] | None:
        """In the background: a stretch of ``drive`` (the scans so far, from ``first_allowed`` on) placed
        over the whole map and confirmed by the next one, among those ending where the drive is now: two,
        four and nine stretches long (room for a first stretch grown twice and four times while ambiguous,
        and its confirmation), the shortest first; then tracked forward to the drive's last scan. (the last
        scan that tracking matched, its map pose, its match score there) or None; the scans after it are
        tracked as they come (:meth:`_take_search`)."""
        c = self._searching
        localizer = Localizer(self.index, drive, c, self.threads, places=self.places)
        travel = drive.travel_m
        candidates: list[int] = []
        for span in (2, 4, 9):
            at = max(int(np.searchsorted(travel, travel[-1] - span * c.stretch_m, side="right")) - 1, 0)
            if at >= first_allowed and at not in candidates and travel[-1] - travel[at] >= 2 * c.stretch_m:
                candidates.append(at)
        for first in candidates:
            placement = localizer.confirmed_placement(first, None)
            self.global_searches += 1
            self.best_score = max(self.best_score, localizer.best_score)
            if placement is None:
                self.failed_tries[localizer._why] = self.failed_tries.get(localizer._why, 0) + 1
                continue
            _, last, pose = placement
            poses = np.full((len(drive), 3), np.nan)
            confidence, tracked = np.zeros(len(drive)), np.zeros(len(drive), bool)
            poses[last] = pose
            _, score = localizer.track(last, pose)  # the placed scan's score there
            confidence[last], tracked[last] = (0.0 if math.isnan(score) else score), True
            localizer.check.reset(confidence[last])
            for j in range(last + 1, len(drive)):
                localizer.step(poses, confidence, tracked, j, j - 1)
            at = int(np.flatnonzero(tracked)[-1])
            return at, poses[at], float(confidence[at])
        return None

    def _take_search(self) -> LivePose | None:
        """A finished background search's outcome: a placement of an earlier scan, carried to the newest
        by tracking the scans that came since. The newest scan's report as it stands now when the drive
        was placed (no report rewritten here), else None."""
        future = self._search
        if future is None or not future.done():
            return None
        self._search = None
        outcome = future.result()
        if outcome is None:
            return None
        at, pose, confidence = outcome
        was_lost = self.state == LOST
        self.poses[at] = pose
        self._last_tracked, self._unmatched_m = at, 0.0
        self._check.reset(confidence)
        self.state = FOUND
        self._event("found", at, jump=was_lost)
        report = LivePose(at, self.t_s[at], pose.copy(), confidence, FOUND)
        for j in range(at + 1, len(self.t_s)):  # scans that arrived while it searched
            report = self._track(j)
        return report

    def _event(self, name: str, k: int, jump: bool = False) -> None:
        event = {"event": name, "t_s": round(self.t_s[k], 3), "scan": k}
        if jump:
            event["search"] = True
        self.events.append(event)

    # --- summary ----------------------------------------------------------------------------------
    def summary(self) -> dict:
        """The drive so far: scans per state, when it was found and lost, the searches made."""
        states = {state: sum(r.state == state for r in self.reports) for state in STATES}
        found = [r.confidence for r in self.reports if r.state == FOUND]
        first = next((r for r in self.reports if r.state == FOUND), None)
        return {"scans": len(self.reports), "states": states, "events": list(self.events),
                "first_found_t_s": None if first is None else round(first.t_s, 3),
                "first_found_travel_m": None if first is None else round(self.travel[first.scan], 3),
                "mean_confidence": round(float(np.mean(found)), 4) if found else None,
                "global_searches": self.global_searches, "failed_tries": dict(self.failed_tries),
                "best_score": round(self.best_score, 4)}
