"""Rao-Blackwellized particle filter SLAM, one message at a time.

Odometry messages move the dead-reckoned odometry pose continuously. A scan is *processed* once
the vehicle has moved ``linear_update_m`` / turned ``angular_update_rad`` (or ``temporal_update_s``
passed) since the last processed scan: every particle samples the odometry motion, fits the scan
onto its own map (scan-matched proposal), is weighted by how well the scan fits there, the set is
resampled when the effective sample size drops, and the scan is inserted into every map. With
``min_particles`` below ``particles``, the count follows the spread of the proposal's poses
(KLD-sampling): a resampling draws as many as it asks for, and where it asks for more than there are,
the heaviest particles are split at once. The
odometry increments are first corrected for the systematic heading error that the matches have
measured so far (:mod:`slam_engine.frontend.heading_calibration`), and each scan is paired with the
odometry at its stamp plus the LiDAR's time offset, estimated online, and de-skewed where the LiDAR
model gives its beams' timing (:mod:`slam_engine.frontend.time_offset`). Other
scans are *skipped*: their pose is the best particle's last pose moved by odometry, refined by a
match against the best particle's map (no map update).

Per-particle trajectories are kept as parent pointers per processed scan (no copied histories);
:meth:`SlamFilter.trajectory` walks the best particle's ancestry back to the first scan.
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numba
import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError
from slam_engine.frontend.grid import ParticleGrids, quantize_log_odds
from slam_engine.frontend.heading_calibration import HeadingCalibration
from slam_engine.frontend.lidar_points import ProjectedScan, ScanProjector
from slam_engine.frontend.motion_models import (
    apply_odometry_increments,
    odometry_increments,
    odometry_motion_covariance,
    odometry_motion_sds,
    sample_odometry_motion,
)
from slam_engine.frontend.odometry import OdometryIntegrator, make_integrator
from slam_engine.frontend.odometry_noise import OdometryPrecision
from slam_engine.frontend.raycast import insert_scan
from slam_engine.frontend.resampling import (
    kld_sample_count,
    low_variance_resample,
    n_eff,
    normalize_log_weights,
    occupied_bins,
)
from slam_engine.frontend.scan_matcher import ScanMatcher
from slam_engine.frontend.time_offset import (
    OdometryHistory,
    TimeOffsetEstimator,
    beam_time_offsets_s,
    matched_turn,
    sweep_poses,
)
from slam_engine.model.drive_log import DriveLog, LidarModel
from slam_engine.model.messages import EncoderMessage, GyroMessage, Message, OdometryMessage, ScanMessage
from slam_engine.model.poses import compose, relative, wrap_angle
from slam_engine.model.result import (
    MapSnapshot,
    OccupancyGrid,
    ScanStats,
    Trajectory,
    preview_pool_factor,
)

THREADS_ENV = "LIDARMAP_THREADS"
# added to the motion covariance [m^2, m^2, rad^2]: a vehicle standing still still has a pose to fuse
MOTION_COV_FLOOR = np.array([1e-6, 1e-6, 1e-7])
# a correlative search precedes the fit when the window is this many times the smallest one (1.5 saved
# intel 4-5 s but lost aces-rough on one seed of five: 2.05 m)
PRESEARCH_BEYOND = 1.0
# how often the particles' maps forget their stale tiles (matcher.local_map_m), in metres of travel
FORGET_EVERY_M = 1.0


def world_motion_information(particles: np.ndarray, motion_cov: np.ndarray) -> np.ndarray:
    """(N, 3, 3) information of the predicted motion in the world frame of each particle's start
    (``particles`` (N, 3)), from its covariance ``motion_cov`` (3, 3, start frame) with a floor (a
    vehicle standing still still has a pose to fuse)."""
    n = len(particles)
    c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
    R = np.zeros((n, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return np.linalg.inv(R @ motion_cov @ R.transpose(0, 2, 1) + np.diag(MOTION_COV_FLOOR))


def fit_surprise(fitted: np.ndarray, predicted: np.ndarray, accepted: np.ndarray, info_fit: np.ndarray,
                 info_motion: np.ndarray) -> np.ndarray:
    """(N,) half the squared Mahalanobis distance of each accepted fit ``fitted`` (N, 3, world) from its
    particle's predicted pose ``predicted`` (N, 3), under the motion's covariance plus the fit's own
    (the inverses of ``info_motion`` and ``info_fit``, (N, 3, 3)); 0 for a rejected fit. Subtracted
    from the scan's log likelihood at the fit, this is the Laplace approximation of the scan's
    likelihood given the motion (Grisetti et al. 2007): a fit far out in the motion's tail weighs
    little, and a direction the scan leaves open (along a corridor: no information) costs nothing.
    On infinite-corridor-rough single particles drawn 3 sd out snapped to false alignments 0.45 rad
    off the prediction (0.09 rad sd), and their lines later won the resampling."""
    # (cov_motion + cov_fit)^-1 = info_motion (info_motion + info_fit)^-1 info_fit, also where info_fit
    # is singular
    info = info_motion @ np.linalg.inv(info_motion + info_fit) @ info_fit
    r = fitted - predicted
    r[:, 2] = wrap_angle(r[:, 2])
    return np.where(accepted, 0.5 * np.einsum("ni,nij,nj->n", r, info, r), 0.0)


def engine_threads() -> int:
    """Threads for the per-particle work (scan matching, map insertion): the environment variable
    ``LIDARMAP_THREADS`` (capped at numba's thread count, all cores by default) or, unset, all of
    numba's. The results do not depend on it."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    # numba.config creates its settings through globals() at import, invisible to its type information
    available: int = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]
    if not raw:
        return available
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError(f"{THREADS_ENV}={raw!r}: expected a whole number of threads >= 1")
    return min(n, available)


def make_projector(lidar: LidarModel, config: SlamConfig, no_return_bounded: bool) -> ScanProjector:
    """The scan projector of ``config``'s grid and LiDAR filter for ``lidar``."""
    g = config.grid
    return ScanProjector(lidar, g.max_range_m, config.lidar_filter.ground_z_m, config.lidar_filter.ceiling_z_m,
                         g.resolution_m, g.no_return_clear_m, g.no_return_min_sensor_range_m, no_return_bounded,
                         g.no_return_stop_short_m)


class ProjectedScans(Sequence[ProjectedScan]):
    """Scans projected by ``projector`` from their ``ranges`` (a list that may still grow) and de-skew
    ``sweeps`` (a list beside it), each when it is read: the projection is deterministic, and a drive
    keeps its ranges (4-8 bytes a beam, usually views into the log) instead of projected end points
    (about 25 bytes a beam)."""

    def __init__(self, projector: ScanProjector, ranges: list[np.ndarray], sweeps: list[np.ndarray | None],
                 angle_offsets: list[float]):
        self.projector = projector
        self.ranges = ranges
        self.sweeps = sweeps  # per scan: its beams' de-skew poses, or None
        self.angle_offsets = angle_offsets  # per scan: its beams' angle offset [rad] (ScanMessage)

    def __len__(self) -> int:
        return len(self.ranges)

    def _one(self, i: int) -> ProjectedScan:
        return self.projector.project(self.ranges[i], self.sweeps[i], self.angle_offsets[i])

    @overload
    def __getitem__(self, index: int) -> ProjectedScan: ...

    @overload
    def __getitem__(self, index: slice) -> list[ProjectedScan]: ...

    def __getitem__(self, index: int | slice) -> ProjectedScan | list[ProjectedScan]:
        if isinstance(index, slice):
            return [self._one(i) for i in range(*index.indices(len(self.ranges)))]
        return self._one(index)

    def __iter__(self) -> Iterator[ProjectedScan]:
        for i in range(len(self.ranges)):
            yield self._one(i)


@dataclass
class _ScanRecord:
    """Where a scan's pose comes from: processed step ``step`` composed with ``offset``."""

    t_s: float
    step: int
    offset: np.ndarray


class SlamFilter:
    """Streaming RBPF SLAM: feed time-ordered messages to :meth:`step`, call :meth:`finish` at the
    end, then read :meth:`trajectory`, :meth:`best_grid` and :meth:`scan_stats`."""

    def __init__(self, lidar: LidarModel, integrator: OdometryIntegrator, config: SlamConfig,
                 rng: np.random.Generator | None = None):
        """``rng`` defaults to ``numpy.random.default_rng(config.seed)`` (same seed, same map)."""
        self.config = config
        self.rng = np.random.default_rng(config.seed) if rng is None else rng
        numba.set_num_threads(engine_threads())  # per calling thread: the one that steps the filter
        self.integrator = integrator
        n = config.particles
        g = config.grid
        # the particles' maps take every no-return beam's evidence (matching needs it); the product map
        # may bound it (grid.no_return_bounded): :meth:`product_scans`
        self.projector = make_projector(lidar, config, no_return_bounded=False)
        self.grids = ParticleGrids(n, g.resolution_m)
        m = config.matcher
        self.matcher = ScanMatcher(m.search_xy_m, m.search_theta_rad, m.min_score, m.beam_skip)
        mo = config.motion
        self.alphas = (mo.rot_from_rot, mo.rot_from_trans, mo.trans_from_trans, mo.trans_from_rot)
        self.heading_calibration = HeadingCalibration(**config.heading_calibration.model_dump())
        self.odometry_precision = OdometryPrecision()
        o = config.odometry
        self.time_offset = TimeOffsetEstimator(
            None if o.time_offset_s == "auto" else float(o.time_offset_s), o.time_offset_max_s,
            o.time_offset_prior_weight, band_s=o.time_offset_band_s, max_se_s=o.time_offset_max_se_s,
            min_steps=o.time_offset_min_steps, min_evidence=o.time_offset_min_evidence)
        self.odometry_history = OdometryHistory(keep_s=2.0 * max(o.time_offset_max_s, abs(self.time_offset.applied_s))
                                                + 1.0)
        self._beam_offsets_s = beam_time_offsets_s(lidar.num_beams, lidar.time_increment_s) if o.deskew else None
        self._beam_poses: np.ndarray | None = None
        # weight of one scan: -(mean squared residual) * independent beams * (res / sigma)^2 / 2
        self.likelihood_gain = m.independent_beams * (g.resolution_m / m.sigma_m) ** 2 / 2.0
        self.particles = np.zeros((n, 3))
        self.log_weights = np.zeros(n)
        self.path_log_likelihood = np.zeros(n)
        self._history: list[np.ndarray] = []
        self._matched: list[np.ndarray] = []  # per step, (N,) bool: the particle's scan match was accepted
        self._parents: list[np.ndarray] = []
        self._next_parents = np.arange(n)
        self._records: list[_ScanRecord] = []
        self.key_frame_ranges: list[np.ndarray] = []  # the ranges [m] of every processed step's scan
        self.key_frame_sweeps: list[np.ndarray | None] = []  # its beams' de-skew poses (None: not de-skewed)
        self.key_frame_angle_offsets: list[float] = []  # its beams' angle offset [rad] (ScanMessage)
        # its projected scan (for the back end), projected again when read
        self.key_frame_scans = ProjectedScans(self.projector, self.key_frame_ranges, self.key_frame_sweeps,
                                              self.key_frame_angle_offsets)
        self.key_frame_odometry: list[np.ndarray] = []  # the odometry pose at it (uncorrected)
        # the wheels' and gyro's cumulative readings at it (None without both: OdometryIntegrator.wheel_check)
        self.key_frame_wheels: list[np.ndarray | None] = []
        self._last_odom: np.ndarray | None = None
        self._last_odom_offset_s = 0.0  # the time offset _last_odom was taken with
        self._last_t_s: float | None = None
        self._pending: deque[ScanMessage] = deque()  # scans waiting for odometry past their stamp
        self._stats: list[tuple[float, float, bool, float, bool, float, int]] = []
        self.snapshots: list[MapSnapshot] = []
        # True: a snapshot every snapshot_every_scans, the newest at preview size for live maps; False:
        # only where each would be (frame_marks), its frame drawn after the back end at the final poses
        self.live_previews = True
        self.frame_marks: list[tuple[int, float]] = []  # (scan index, time [s]) of each frame, offline
        self._last_forget_m = 0.0  # the maps' travel clock [m] when stale tiles were last forgotten

    @classmethod
    def from_log(cls, log: DriveLog, config: SlamConfig, rng: np.random.Generator | None = None) -> SlamFilter:
        """A filter for ``log``'s LiDAR and odometry source (ConfigError when it has none)."""
        if log.lidar is None:
            raise ValueError("the log has no LiDAR model")
        return cls(log.lidar, make_integrator(log), config, rng)

    # --- streaming ------------------------------------------------------------------------
    @property
    def scans_seen(self) -> int:
        return len(self._records) + len(self._pending)

    @property
    def steps_processed(self) -> int:
        return len(self._history)

    def step(self, message: Message) -> None:
        """Consume one message (messages must come in time order). A scan is handled once the
        odometry has reached its stamp plus :meth:`_lookahead_s`, or when a scan that much later arrives."""
        if isinstance(message, (EncoderMessage, GyroMessage, OdometryMessage)):
            if self.integrator.update(message):
                assert self.integrator.t_s is not None  # an update that advanced the pose set its time
                self.odometry_history.append(self.integrator.t_s, self.integrator.pose)
                self.time_offset.update(self.odometry_history)
                while self._pending and self.integrator.t_s >= self._pending[0].t_s + self._lookahead_s():
                    self._handle_scan(self._pending.popleft())
        elif isinstance(message, ScanMessage):
            while self._pending and message.t_s >= self._pending[0].t_s + self._lookahead_s():
                self._handle_scan(self._pending.popleft())
            if not self._pending and self.integrator.t_s is not None \
                    and self.integrator.t_s >= message.t_s + self._lookahead_s():
                self._handle_scan(message)
            else:
                self._pending.append(message)

    def finish(self) -> None:
        """Handle the scans still waiting for odometry (with the last odometry pose)."""
        while self._pending:
            self._handle_scan(self._pending.popleft())
        self.time_offset.update(self.odometry_history, final=True)

    def _lookahead_s(self) -> float:
        """How far past a scan's stamp the odometry must reach before the scan is handled [s]: its
        time offset plus half its sweep, when positive."""
        sweep = 0.0 if self._beam_offsets_s is None else float(np.abs(self._beam_offsets_s).max())
        return max(0.0, self.time_offset.applied_s + sweep)

    def _odom_at(self, t_s: float) -> np.ndarray:
        """The odometry pose at ``t_s`` (odometry clock): from the integrator's last two poses while
        scans are paired at their stamps without de-skew (the pairing of a log without an offset stays
        exactly as it was), else from the odometry history."""
        if self.integrator.t_s is None:
            return np.zeros(3)
        if self.time_offset.applied_s == 0.0 and self._beam_offsets_s is None:
            return self.integrator.pose_at(t_s)
        return self.odometry_history.pose_at(t_s)

    def _handle_scan(self, scan: ScanMessage) -> None:
        start = time.perf_counter()
        offset_s = self.time_offset.applied_s
        odom = self._odom_at(scan.t_s + offset_s)
        self._beam_poses = None
        if self._beam_offsets_s is not None and len(self.odometry_history):
            self._beam_poses = sweep_poses(self.odometry_history, scan.t_s + offset_s, self._beam_offsets_s,
                                           self.heading_calibration.applied_scale)
        projected = self.projector.project(scan.ranges_m, self._beam_poses, scan.angle_offset_rad)
        self._ranges_m = scan.ranges_m
        self._angle_offset_rad = scan.angle_offset_rad
        if self._last_odom is not None and offset_s != self._last_odom_offset_s and self._last_t_s is not None \
                and self.odometry_history.covers(self._last_t_s + offset_s):
            # the offset changed since the last processed scan: take its odometry pose with the new one
            self._last_odom = self._odom_at(self._last_t_s + offset_s)
            self._last_odom_offset_s = offset_s
        if self._last_odom is None:
            self._first_scan(scan, odom, projected)
        elif self._due(scan.t_s, odom):
            self._process(scan, odom, projected)
        else:
            self._skip(scan, odom, projected)
            return
        self._stats[-1] = self._stats[-1][:5] + (time.perf_counter() - start,) + self._stats[-1][6:]
        every = self.config.snapshot_every_scans
        if every and self.steps_processed % every == 0:
            if not self.live_previews:  # the frame is drawn by the pipeline, after the back end
                self.frame_marks.append((len(self._records) - 1, scan.t_s))
            else:
                if self.snapshots:  # kept for the animation: a frame's size is enough
                    self.snapshots[-1] = self.snapshots[-1].reduced()
                self.snapshots.append(MapSnapshot(scan_index=len(self._records) - 1, t_s=scan.t_s,
                                                  grid=self.preview_grid(), trajectory=self.trajectory()))

    def _due(self, t_s: float, odom: np.ndarray) -> bool:
        assert self._last_odom is not None and self._last_t_s is not None  # set by the first scan's step
        s = self.config.scheduling
        _, trans, _ = odometry_increments(self._last_odom, odom)
        turn = abs(relative(self._last_odom, odom)[2])
        waited = s.temporal_update_s > 0 and t_s - self._last_t_s >= s.temporal_update_s
        return bool(abs(trans) >= s.linear_update_m or turn >= s.angular_update_rad or waited)

    def _first_scan(self, scan: ScanMessage, odom: np.ndarray, projected) -> None:
        g = self.config.grid
        insert_scan(self.grids, self.particles[:1], self.projector.origin_v, projected.ends_v, projected.is_hit,
                    g.log_odds_hit, g.log_odds_miss, g.log_odds_min, g.log_odds_max, projected.free_from_m)
        self.grids.resample(np.zeros(self.config.particles, np.int64))  # every particle shares that map
        self.time_offset.record_step(scan.t_s, None)
        self._record_step(scan.t_s, odom, projected, np.ones(self.config.particles, bool))
        self._stats.append((scan.t_s, float(self.config.particles), False, 1.0, False, 0.0, self.config.particles))

    def _record_step(self, t_s: float, odom: np.ndarray, projected: ProjectedScan, matched: np.ndarray) -> None:
        self._history.append(self.particles.copy())
        self._matched.append(np.asarray(matched, bool).copy())
        self.key_frame_odometry.append(np.asarray(odom, np.float64).copy())
        self.key_frame_wheels.append(self.integrator.wheel_check())
        self.key_frame_ranges.append(self._ranges_m)
        self.key_frame_sweeps.append(self._beam_poses)
        self.key_frame_angle_offsets.append(self._angle_offset_rad)
        self._parents.append(self._next_parents)
        self._next_parents = np.arange(len(self.particles))
        self._records.append(_ScanRecord(t_s, len(self._history) - 1, np.zeros(3)))
        self._last_odom = odom
        self._last_odom_offset_s = self.time_offset.applied_s
        self._last_t_s = t_s

    def _match_points(self, projected) -> np.ndarray:
        """The end points used for matching: returns only, thinned to at most ``max_points``."""
        hits = projected.hits_v
        budget = self.config.matcher.max_points
        if len(hits) > budget:
            hits = hits[:: int(np.ceil(len(hits) / budget))]
        return hits

    def _process(self, scan: ScanMessage, odom: np.ndarray, projected) -> None:
        assert self._last_odom is not None  # set by the first scan's step
        n = len(self.particles)
        target = self.heading_calibration.corrected_target(self._last_odom, odom)
        # the motion model scaled to the odometry's measured precision (the configured one unless the
        # odometry has proved more precise than the matches)
        precision = self.odometry_precision
        alphas = precision.scaled(self.alphas)
        sampled = sample_odometry_motion(self.particles, self._last_odom, target, alphas, self.rng)
        self._forget_stale_map(odom)
        hits = self._match_points(projected)
        if len(hits) >= 3:
            motion_cov = odometry_motion_covariance(self._last_odom, target, alphas)
            fused = precision.trusted or self.config.matcher.proposal == "fused"
            predicted = apply_odometry_increments(self.particles, *odometry_increments(self._last_odom, target))
            poses, log_lik, score, accepted, jtj, fitted = self._propose(sampled, predicted, motion_cov, hits, fused)
            # the configured model's spread of this motion, against which the precision is measured
            sd_rot1, sd_trans, sd_rot2 = odometry_motion_sds(self._last_odom, target, self.alphas)
            leader = int(np.argmax(self.log_weights + log_lik))
            precision.observe(fitted[leader], odom, sd_trans, math.hypot(sd_rot1, sd_rot2),
                              self.integrator.wheel_check())
            self.heading_calibration.observe(self._last_odom, odom, self.particles, poses, accepted)
            self.heading_calibration.observe_distance(self._last_odom, odom, self.particles, poses, accepted, jtj)
            hc = self.heading_calibration
            self.time_offset.record_step(scan.t_s, matched_turn(self.particles, poses, accepted),
                                         odometry_increments(self._last_odom, odom)[1], hc.scale, hc.drift_rad_per_m)
        else:
            poses, score, accepted, log_lik = sampled, np.zeros(n), np.zeros(n, bool), np.zeros(n)
            self.time_offset.record_step(scan.t_s, None)
        self.particles = poses
        self.log_weights = self.log_weights + log_lik
        self.path_log_likelihood = self.path_log_likelihood + log_lik
        best = self.best_particle()
        weights = normalize_log_weights(self.log_weights)
        neff = n_eff(weights)
        count = self._particles_needed()
        resampled = neff < self.config.resample_threshold * n  # fewer particles only then
        # the history holds the poses before resampling; the next step's parents say who survived
        self._record_step(scan.t_s, odom, projected, accepted)
        clones_of = None
        if resampled:
            clones_of = low_variance_resample(weights, self.rng, count)
            self._take(clones_of, np.zeros(count))
        elif count > n:
            clones_of = self._split(weights, count)
        self._insert(projected, clones_of)
        self._stats.append((scan.t_s, neff, bool(resampled), float(score[best]), bool(accepted[best]), 0.0,
                            len(self.particles)))

    def _split(self, weights: np.ndarray, count: int) -> np.ndarray:
        """Grow the set to ``count`` particles without resampling (which would throw the weights away):
        the heaviest particles are split, each copy keeping the pose and the map with an equal share
        of the weight, so the distribution the set stands for is unchanged. Returns the ancestors."""
        n = len(self.particles)
        order = np.argsort(-weights, kind="stable")
        ancestors = np.concatenate([np.arange(n), order[np.arange(count - n) % n]])
        copies = np.bincount(ancestors, minlength=n)
        self._take(ancestors, (self.log_weights - np.log(copies))[ancestors])
        return ancestors

    def _take(self, ancestors: np.ndarray, log_weights: np.ndarray) -> None:
        """The new set: particle i is a copy of particle ``ancestors[i]`` (pose, path likelihood, map),
        with ``log_weights[i]``; the next step's parents say who it came from."""
        self.particles = self.particles[ancestors]
        self.path_log_likelihood = self.path_log_likelihood[ancestors]
        self.log_weights = log_weights
        self.grids.resample(ancestors)
        self._next_parents = ancestors

    def _particles_needed(self) -> int:
        """How many particles the set should hold: ``particles``, or with ``min_particles``
        below it, KLD-sampling's count for the bins (``kld_bin_xy_m``, ``kld_bin_theta_rad``) that the
        current poses occupy, within ``[min_particles, particles]``. Every current pose counts, also
        those about to lose the resampling: the count errs on the side of more."""
        c = self.config
        fewest = min(c.min_particles, c.particles)
        if fewest >= c.particles:
            return c.particles
        bins = occupied_bins(self.particles, c.kld_bin_xy_m, c.kld_bin_theta_rad)
        return int(np.clip(kld_sample_count(bins, c.kld_error), fewest, c.particles))

    def _forget_stale_map(self, odom: np.ndarray) -> None:
        """Advance the maps' travel clock by the odometry's translation since the last step and, every
        ``FORGET_EVERY_M``, forget the tiles untouched for ``matcher.local_map_m`` (0: never)."""
        assert self._last_odom is not None  # set by the first scan's step
        horizon = self.config.matcher.local_map_m
        grids = self.grids
        grids.clock_m += float(np.hypot(odom[0] - self._last_odom[0], odom[1] - self._last_odom[1]))
        if horizon <= 0 or grids.clock_m - self._last_forget_m < FORGET_EVERY_M:
            return
        g = self.config.grid
        grids.forget_stale(grids.clock_m - horizon, self.best_particle(), quantize_log_odds(g.log_odds_min),
                           quantize_log_odds(g.log_odds_max))
        self._last_forget_m = grids.clock_m

    def _search_window(self, motion_cov: np.ndarray) -> tuple[float, float]:
        """Half widths [m, rad] of the matcher's window: ``search_sigmas`` standard deviations of the
        predicted motion error, within the configured smallest and largest windows."""
        m = self.config.matcher
        sd_xy = float(np.sqrt(max(np.linalg.eigvalsh(motion_cov[:2, :2]).max(), 0.0)))
        sd_theta = float(np.sqrt(max(motion_cov[2, 2], 0.0)))
        return (float(np.clip(m.search_sigmas * sd_xy, m.search_xy_m, max(m.search_xy_m, m.max_search_xy_m))),
                float(np.clip(m.search_sigmas * sd_theta, m.search_theta_rad,
                              max(m.search_theta_rad, m.max_search_theta_rad))))

    def _propose(self, sampled: np.ndarray, predicted: np.ndarray, motion_cov: np.ndarray, hits: np.ndarray,
                 fused: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The scan-matched proposal: each particle's scan is fitted from its motion sample
        ``sampled`` (N, 3) within a window sized by the motion covariance ``motion_cov`` (3, 3, start
        frame), searched correlatively first where that window is wider than the Gauss-Newton basin.
        A sample drawn far out in the motion's tail can leave the truth outside its window: where its
        match is rejected, the fit is tried again from the motion's mean ``predicted`` (N, 3) before
        the particle falls back to its sample (on infinite-corridor-rough, particles that kept samples
        15-19 deg off at corners, with maps built on them, later won the resampling: the best path
        turned that much in one step).
        With ``fused`` (``matcher.proposal = "fused"``, or odometry measured to be more precise than
        the matches: :class:`OdometryPrecision`) the fit is then combined with the sample by their
        information (the fit's Gauss-Newton matrix, the inverse motion covariance; Grisetti et al.
        2007), so that precise odometry is kept along directions the scan leaves open. A rejected
        match keeps the motion sample. Weights: the likelihood of the scan at the fitted pose, less
        ``matcher.motion_prior`` times :func:`fit_surprise` (how far out in the motion's spread the fit lies).
        Returns (poses, log weight increments, mean scores, accepted, the fits' J^T J (N, 3, 3), the
        fitted poses before any fusion)."""
        m = self.config.matcher
        n = len(sampled)
        gain = self.likelihood_gain / len(hits)
        window_xy, window_theta = self._search_window(motion_cov)
        presearch = None
        info_o = None
        # the fit's own basin covers the smallest window and a good deal more: search first only
        # where the window is well beyond it
        wide = window_xy > PRESEARCH_BEYOND * m.search_xy_m or window_theta > PRESEARCH_BEYOND * m.search_theta_rad
        if wide or fused or m.motion_prior > 0:
            info_o = world_motion_information(self.particles, motion_cov)
        if wide:
            # translations only where their window exceeds the fit's basin (a turn on the spot needs
            # headings alone); headings always: a wrong heading is what loses a map
            assert info_o is not None  # computed above whenever the window is wide
            mean_info = info_o.mean(axis=0)
            presearch = np.array([window_xy if window_xy > PRESEARCH_BEYOND * m.search_xy_m else 0.0, window_theta,
                                  self.likelihood_gain, mean_info[0, 0], mean_info[1, 1], mean_info[2, 2]])
        fit = self.matcher.fit(self.grids, np.arange(n), sampled, hits, window_xy, window_theta, presearch)
        rejected = np.flatnonzero(~fit.accepted)
        if len(rejected):
            again = self.matcher.fit(self.grids, rejected, predicted[rejected], hits, window_xy, window_theta,
                                     presearch)
            took = rejected[again.accepted]
            for mine, theirs in ((fit.poses, again.poses), (fit.sq_residual, again.sq_residual),
                                 (fit.mean_score, again.mean_score), (fit.accepted, again.accepted),
                                 (fit.jtj, again.jtj)):
                mine[took] = theirs[again.accepted]
        poses = fit.poses.copy()
        log_lik = -gain * fit.sq_residual
        info_m = m.proposal_information * 2.0 * gain * fit.jtj
        if m.motion_prior > 0:
            assert info_o is not None  # computed above whenever the prior is weighed
            log_lik = log_lik - m.motion_prior * fit_surprise(fit.poses, predicted, fit.accepted, info_m, info_o)
        if fused:
            assert info_o is not None  # computed above for the fused proposal
            to_match = fit.poses - sampled
            to_match[:, 2] = wrap_angle(to_match[:, 2])
            combined = sampled + np.einsum("nij,njk,nk->ni", np.linalg.inv(info_m + info_o), info_m, to_match)
            combined[:, 2] = wrap_angle(combined[:, 2])
            poses = np.where(fit.accepted[:, None], combined, poses)
        return poses, log_lik, fit.mean_score, fit.accepted, fit.jtj, fit.poses

    def _insert(self, projected, clones_of: np.ndarray | None) -> None:
        """Insert the scan into every particle's map. Particles with the same ``clones_of`` entry
        (copies of one ancestor after resampling: same pose, same map) get one insertion, into the
        first of them, whose map the others then share: the same maps as inserting into each."""
        g = self.config.grid
        particles = None
        if clones_of is not None:
            _, first, inverse = np.unique(clones_of, return_index=True, return_inverse=True)
            if len(first) < len(clones_of):
                particles = first
        poses = self.particles if particles is None else self.particles[particles]
        insert_scan(self.grids, poses, self.projector.origin_v, projected.ends_v, projected.is_hit,
                    g.log_odds_hit, g.log_odds_miss, g.log_odds_min, g.log_odds_max, projected.free_from_m,
                    particles=particles)
        if particles is not None:
            self.grids.resample(particles[inverse])

    def _skip(self, scan: ScanMessage, odom: np.ndarray, projected) -> None:
        assert self._last_odom is not None  # set by the first scan's step
        best = self.best_particle()
        current = self.particles[best]  # equals its recorded pose at the last processed step
        predicted = compose(current, relative(self._last_odom,
                                              self.heading_calibration.corrected_target(self._last_odom, odom)))
        pose = predicted
        hits = self._match_points(projected)
        if len(hits) >= 3:
            fitted, _, _, accepted = self.matcher.match(self.grids, np.array([best]), predicted[None, :], hits)
            if accepted[0]:
                pose = fitted[0]
        self._records.append(_ScanRecord(scan.t_s, len(self._history) - 1, relative(current, pose)))

    def _parent_of_current(self, i: int) -> int:
        """Index in the last recorded step of current particle ``i`` (its ancestor when resampled)."""
        return int(self._next_parents[i])

    # --- results --------------------------------------------------------------------------
    def best_particle(self) -> int:
        """Index of the particle with the highest weight (path likelihood breaks ties)."""
        top = self.log_weights.max()
        candidates = np.flatnonzero(self.log_weights >= top - 1e-9)
        return int(candidates[np.argmax(self.path_log_likelihood[candidates])])

    def _best_ancestry(self) -> np.ndarray:
        """(steps,) index, in every processed step's record, of the best particle's ancestor there."""
        k_total = len(self._history)
        ancestry = np.empty(k_total, np.int64)
        idx = self._parent_of_current(self.best_particle())
        for k in range(k_total - 1, -1, -1):
            ancestry[k] = idx
            idx = int(self._parents[k][idx])
        return ancestry

    def key_frame_path(self) -> np.ndarray:
        """(steps, 3) poses of the best particle's ancestry at every processed scan (key frame)."""
        ancestry = self._best_ancestry()
        return np.array([self._history[k][i] for k, i in enumerate(ancestry)]).reshape(-1, 3)

    def key_frame_matched(self) -> np.ndarray:
        """(steps,) bool: whether the best particle's ancestry matched its scan at every processed step
        (False: the step's pose is its motion sample, unverified by the scan; the first step counts as
        matched)."""
        ancestry = self._best_ancestry()
        return np.array([self._matched[k][i] for k, i in enumerate(ancestry)], bool)

    def key_frame_times(self) -> np.ndarray:
        """(steps,) time [s] of the scan processed at every step (key frame)."""
        times = np.full(len(self._history), np.nan)
        for record in reversed(self._records):  # a step's first record is its own scan's
            times[record.step] = record.t_s
        return times

    def trajectory(self, key_frame_poses: np.ndarray | None = None) -> Trajectory:
        """Best particle's trajectory, one pose per scan handled so far; with ``key_frame_poses``
        (steps, 3), e.g. the back end's optimised key frames, the scans between them follow those."""
        if not self._records:
            return Trajectory(t_s=np.zeros(0), poses=np.zeros((0, 3)))
        path = self.key_frame_path() if key_frame_poses is None else key_frame_poses
        steps = np.array([r.step for r in self._records])
        offsets = np.array([r.offset for r in self._records])
        return Trajectory(t_s=np.array([r.t_s for r in self._records]), poses=compose(path[steps], offsets))

    def product_scans(self) -> Sequence[ProjectedScan]:
        """The key frames' scans as the product map takes them: with ``grid.no_return_bounded`` a
        beam without a return clears only up to its bracketing returns (no halo around buildings)."""
        if not self.config.grid.no_return_bounded:
            return self.key_frame_scans
        bounded = make_projector(self.projector.lidar, self.config, no_return_bounded=True)
        return ProjectedScans(bounded, self.key_frame_ranges, self.key_frame_sweeps, self.key_frame_angle_offsets)

    def best_grid(self) -> OccupancyGrid:
        return self.grids.occupancy_grid(self.best_particle())

    def preview_grid(self) -> OccupancyGrid:
        """The best particle's map pooled to at most about ``PREVIEW_MAX_SIDE_CELLS`` a side (what a
        live preview shows; the full map of a long drive would be hundreds of MB), built without
        the full-resolution grid."""
        best = self.best_particle()
        return self.grids.occupancy_grid(best, pool=preview_pool_factor(max(self.grids.observed_shape(best))))

    def scan_stats(self) -> ScanStats:
        rows = self._stats
        col = list(zip(*rows, strict=True)) if rows else [()] * 7
        return ScanStats(t_s=np.array(col[0], float), n_eff=np.array(col[1], float),
                         resampled=np.array(col[2], bool), match_score=np.array(col[3], float),
                         matched=np.array(col[4], bool), step_time_s=np.array(col[5], float),
                         particles=np.array(col[6], np.int64))
