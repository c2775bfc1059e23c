"""One map from two: a saved map extended by a new drive, or two saved maps merged.

The second part (a new drive's own map, or another saved map) is placed in the first map's frame by
:mod:`~slam_engine.multisession.localization` (its key frames, at their poses in their own map, are the
"drive"). Both parts' key frames then go through the back end as one drive: the loop closer looks for
closures everywhere, across the two parts too (their junction is a loose, unverified motion edge, so it
is the closures that tie them), one pose graph is optimised, every key frame is fitted to the joint map,
and the occupancy grid is rendered from both parts' scans. The first map may move where the second part
proves it wrong. A part that cannot be placed is kept beside the map as a *disconnected* drive (its poses
in its own frame) and placed again whenever the map is extended later.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from slam_engine.backend.loop_closer import close_loops
from slam_engine.backend.map_alignment import align_to_map
from slam_engine.backend.map_builder import render_occupancy
from slam_engine.config import SlamConfig
from slam_engine.errors import MapBundleError
from slam_engine.evaluation.consistency import MapConsistency, map_consistency
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.poses import compose, relative
from slam_engine.model.result import OccupancyGrid, Trajectory
from slam_engine.multisession.localization import (
    DriveScans,
    LocalizationResult,
    localize,
    map_places_of,
    refusal_reason,
)


@dataclass
class JoinedMap:
    """The joint map: its ``bundle`` (both parts, map frame of the first), the occupancy ``grid``, the
    per-scan ``trajectory`` of every connected drive (``trajectory_drive`` numbers them), the
    ``placement`` of the second part and the back end's summary."""

    bundle: MapBundle
    grid: OccupancyGrid
    trajectory: Trajectory
    trajectory_drive: np.ndarray
    placement: LocalizationResult
    connected: bool
    summary: dict = field(default_factory=dict)
    wall_time_s: float = 0.0
    consistency: MapConsistency | None = None  # of ``grid`` with the connected drives' key frames
    part_drives: list[int] = field(default_factory=list)  # the second part's drives, as numbered in ``bundle``


def place_part(base: MapBundle, part: MapBundle, config: SlamConfig, threads: int = 1) -> LocalizationResult:
    """Where ``part``'s key frames (poses in their own map frame) lie in ``base``'s map (its own loops are
    closed already: the joint back end closes them again with the map's)."""
    settings = config.model_copy(update={"localization": config.localization.model_copy(update={"own_loops": False})})
    return localize(base, DriveScans.from_bundle(part), settings, threads=threads)


def join(base: MapBundle, part: MapBundle, config: SlamConfig, threads: int = 1) -> JoinedMap:
    """``base`` and ``part`` as one map (see the module docstring). Drives of ``base`` that were left
    disconnected are placed again in the joint map; ``part``'s drives are numbered after ``base``'s."""
    started = time.perf_counter()
    joint, loose = split_connected(base)
    part = renumbered(part, first_drive=base.drives)
    placement: LocalizationResult | None = None
    left: list[MapBundle] = []
    for candidate in [part, *_drives_of(loose)]:  # the new part, then drives that could not be placed before
        placed = place_part(joint, candidate, config, threads)
        placement = placed if placement is None else placement
        if placed.localised:
            assert placed.T_map_from_drive is not None
            joint = _optimised(concatenated(joint, moved(candidate, placed.T_map_from_drive)), config, threads)
        else:
            left.append(candidate)
    assert placement is not None
    joint = pruned(joint, config)
    bundle = joint
    for candidate in left:
        bundle = concatenated(bundle, candidate, connect=False)
    # its place index, kept with it as a mapping run's is (of the connected map: the parts left beside it
    # are in frames of their own)
    bundle.places = map_places_of(joint, config.place_index).stored(config.place_index.spacing_m)
    grid = render_occupancy(joint.scans(), joint.poses, joint.origin_v, config.grid)
    consistency = map_consistency(grid, joint.poses, joint.all_hits())
    keep = ~np.isin(bundle.trajectory_drive, disconnected_drives(bundle))
    return JoinedMap(bundle, grid, Trajectory(bundle.trajectory_t_s[keep], bundle.trajectory[keep]),
                     bundle.trajectory_drive[keep], placement, placement.localised,
                     {"placement": placement.summary(), "connected_drives": sorted(set(joint.drive.tolist())),
                      "disconnected_drives": disconnected_drives(bundle),
                      "loop_closing": bundle.sensors.get("last_join")},
                     time.perf_counter() - started, consistency, sorted(set(part.drive.tolist())))


def pruned(bundle: MapBundle, config: SlamConfig) -> MapBundle:
    """``bundle`` with at most ``localization.max_map_key_frames`` key frames: while over, the key frames
    of the oldest drives that a key frame of a newer drive sees from within ``prune_m`` / ``prune_rad``
    are dropped, oldest first (a place driven again and again keeps its newest views); when that is not
    enough, the older drives are thinned (every other key frame, oldest drive first). Each drive keeps
    its first and last key frame; the pose graph is rebuilt from the poses at the next join, so the
    dropped key frames leave a longer motion between their neighbours. Every scan's pose is kept."""
    from scipy.spatial import cKDTree

    c = config.localization
    excess = len(bundle) - c.max_map_key_frames
    if excess <= 0:
        return bundle
    keep = np.ones(len(bundle), bool)
    newest = int(bundle.drive.max())
    for drive in sorted(set(bundle.drive.tolist())):
        if drive == newest or excess <= 0:
            break
        newer = np.flatnonzero(bundle.drive > drive)
        tree = cKDTree(bundle.poses[newer, :2])
        frames = np.flatnonzero(bundle.drive == drive)[1:-1]
        for k, near in zip(frames, tree.query_ball_point(bundle.poses[frames, :2], c.prune_m), strict=True):
            turn = np.abs(np.angle(np.exp(1j * (bundle.poses[newer[near], 2] - bundle.poses[k, 2]))))
            if excess > 0 and np.any(turn <= c.prune_rad):
                keep[k] = False
                excess -= 1
    while excess > 0:  # still over: the older drives thinned, every other key frame, oldest first
        before = excess
        for drive in sorted(set(bundle.drive.tolist()))[:-1]:
            interior = np.flatnonzero(keep & (bundle.drive == drive))[1:-1]
            for k in interior[::2][:excess]:
                keep[k] = False
            excess -= min(len(interior[::2]), excess)
        if excess == before:
            break  # nothing left to thin (the newest drive alone is over the cap)
    return subset(bundle, keep)


def disconnected_drives(bundle: MapBundle) -> list[int]:
    """Drives of ``bundle`` kept beside the map (not placed in it), from its ``disconnected`` config key."""
    return [int(d) for d in bundle.sensors.get("disconnected_drives", [])]


def split_connected(bundle: MapBundle) -> tuple[MapBundle, MapBundle]:
    """``bundle``'s connected key frames and its disconnected ones, as two bundles."""
    loose = np.isin(bundle.drive, disconnected_drives(bundle))
    return subset(bundle, ~loose), subset(bundle, loose)


def _drives_of(bundle: MapBundle) -> list[MapBundle]:
    return [subset(bundle, bundle.drive == d) for d in np.unique(bundle.drive)]


def subset(bundle: MapBundle, keep: np.ndarray) -> MapBundle:
    """The key frames ``keep`` (K,) bool of ``bundle``, their scans, the edges between them and their
    drives' trajectories."""
    index = np.flatnonzero(keep)
    new_of = np.full(len(bundle), -1, np.int64)
    new_of[index] = np.arange(len(index))
    rows = [np.arange(bundle.scan_offsets[k], bundle.scan_offsets[k + 1]) for k in index]
    rows_all = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    counts = np.array([len(r) for r in rows], np.int64)
    edge_keep = keep[bundle.edges_ij[:, 0]] & keep[bundle.edges_ij[:, 1]] if len(bundle.edges_ij) else np.zeros(0, bool)
    traj_keep = np.isin(bundle.trajectory_drive, np.unique(bundle.drive[index]))
    sensors = dict(bundle.sensors)
    sensors["disconnected_drives"] = [d for d in disconnected_drives(bundle) if d in set(bundle.drive[index].tolist())]
    return MapBundle(
        poses=bundle.poses[index], t_s=bundle.t_s[index], drive=bundle.drive[index],
        unverified=bundle.unverified[index], scan_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        ends_v=bundle.ends_v[rows_all], is_hit=bundle.is_hit[rows_all], free_from_m=bundle.free_from_m[rows_all],
        origin_v=bundle.origin_v, edges_ij=new_of[bundle.edges_ij[edge_keep]].reshape(-1, 2),
        edges_T_i_from_j=bundle.edges_T_i_from_j[edge_keep], edges_sigmas=bundle.edges_sigmas[edge_keep],
        edges_robust=bundle.edges_robust[edge_keep], trajectory_t_s=bundle.trajectory_t_s[traj_keep],
        trajectory=bundle.trajectory[traj_keep], trajectory_drive=bundle.trajectory_drive[traj_keep],
        resolution_m=bundle.resolution_m, config=bundle.config, sensors=sensors)


def renumbered(bundle: MapBundle, first_drive: int) -> MapBundle:
    """``bundle`` with its drives numbered from ``first_drive`` on."""
    shift = first_drive - (int(bundle.drive.min()) if len(bundle.drive) else 0)
    out = subset(bundle, np.ones(len(bundle), bool))
    out.drive = bundle.drive + shift
    out.trajectory_drive = bundle.trajectory_drive + shift
    out.sensors = {**out.sensors, "disconnected_drives": [d + shift for d in disconnected_drives(bundle)]}
    return out


def moved(bundle: MapBundle, T_new_from_old: np.ndarray) -> MapBundle:
    """``bundle`` with every pose expressed in a new frame (``T_new_from_old``: the old frame in the new)."""
    out = subset(bundle, np.ones(len(bundle), bool))
    out.poses = compose(T_new_from_old, bundle.poses)
    out.trajectory = compose(T_new_from_old, bundle.trajectory)
    return out


def concatenated(first: MapBundle, second: MapBundle, connect: bool = True) -> MapBundle:
    """One bundle of ``first``'s key frames then ``second``'s (both in one frame); ``connect`` False keeps
    ``second``'s drives as disconnected ones."""
    n = len(first)
    unverified = np.concatenate([first.unverified, second.unverified])
    if len(second):
        unverified[n] = True  # the junction: nothing measured ties the parts there
    disconnected = disconnected_drives(first) + disconnected_drives(second)
    if not connect:
        disconnected += sorted(set(np.unique(second.drive).tolist()) - set(disconnected))
    return MapBundle(
        poses=np.concatenate([first.poses, second.poses]), t_s=np.concatenate([first.t_s, second.t_s]),
        drive=np.concatenate([first.drive, second.drive]), unverified=unverified,
        scan_offsets=np.concatenate([first.scan_offsets, second.scan_offsets[1:] + first.scan_offsets[-1]]),
        ends_v=np.concatenate([first.ends_v, second.ends_v]), is_hit=np.concatenate([first.is_hit, second.is_hit]),
        free_from_m=np.concatenate([first.free_from_m, second.free_from_m]), origin_v=first.origin_v,
        edges_ij=np.concatenate([first.edges_ij, second.edges_ij + n]),
        edges_T_i_from_j=np.concatenate([first.edges_T_i_from_j, second.edges_T_i_from_j]),
        edges_sigmas=np.concatenate([first.edges_sigmas, second.edges_sigmas]),
        edges_robust=np.concatenate([first.edges_robust, second.edges_robust]),
        trajectory_t_s=np.concatenate([first.trajectory_t_s, second.trajectory_t_s]),
        trajectory=np.concatenate([first.trajectory, second.trajectory]),
        trajectory_drive=np.concatenate([first.trajectory_drive, second.trajectory_drive]),
        resolution_m=first.resolution_m, config=first.config,
        sensors={**first.sensors, "disconnected_drives": sorted(disconnected)})


def _optimised(bundle: MapBundle, config: SlamConfig, threads: int) -> MapBundle:
    """``bundle``'s key frames through the back end as one drive: loop closing (across its drives too),
    one pose graph, the fit to the joint map; every scan's pose re-anchored to its key frame's new pose."""
    hits = bundle.all_hits()
    c = config.loop_closing
    backend = close_loops(bundle.poses, hits, c, bundle.resolution_m, unverified=bundle.unverified, threads=threads,
                          places=config.place_index.for_far_searches())
    poses = backend.poses
    if c.enabled:
        poses, _ = align_to_map(poses, hits, bundle.resolution_m, c.map_alignment_passes, c.match_range_m)
    out = subset(bundle, np.ones(len(bundle), bool))
    out.poses = np.asarray(poses, np.float64)
    out.trajectory = reanchored(bundle, out.poses)
    out.edges_ij = np.array([(e.i, e.j) for e in backend.edges], np.int64).reshape(-1, 2)
    out.edges_T_i_from_j = np.array([e.T_i_from_j for e in backend.edges], np.float64).reshape(-1, 3)
    out.edges_sigmas = np.array([e.sigmas for e in backend.edges], np.float64).reshape(-1, 3)
    out.edges_robust = np.array([e.robust for e in backend.edges], bool)
    summary = backend.summary()
    summary.pop("closures")
    out.sensors = {**out.sensors, "last_join": summary}
    return out


def reanchored(bundle: MapBundle, new_poses: np.ndarray) -> np.ndarray:
    """Every scan's pose of ``bundle``'s trajectory moved with its drive's nearest key frame (in time)
    from ``bundle.poses`` to ``new_poses``."""
    out = bundle.trajectory.copy()
    for d in np.unique(bundle.trajectory_drive):
        scans = np.flatnonzero(bundle.trajectory_drive == d)
        frames = np.flatnonzero(bundle.drive == d)
        if len(frames) == 0:
            continue
        t_frames = bundle.t_s[frames]
        nearest = frames[np.clip(np.searchsorted(t_frames, bundle.trajectory_t_s[scans], side="right") - 1, 0,
                                 len(frames) - 1)]
        local = relative(bundle.poses[nearest], bundle.trajectory[scans])
        out[scans] = compose(new_poses[nearest], local)
    return out


def merge(first: MapBundle, second: MapBundle, config: SlamConfig, threads: int = 1) -> JoinedMap:
    """Two saved maps of one place as one; :class:`MapBundleError` when the second cannot be placed in the
    first (they do not overlap, or not enough to be sure)."""
    joined = join(first, second, config, threads)
    if not joined.connected:
        raise MapBundleError(f"the maps do not overlap: the second map could not be placed in the first: "
                             f"{refusal_reason(joined.placement, config.localization.min_score)}")
    return joined

