"""One SLAM run over a whole drive log: the loop, the timing, the progress reports.

Progress goes through named stages, in order (:mod:`slam_engine.progress`): the front end maps the
scans, the back end closes loops and aligns the key frames to the map, the product map is rendered; the
caller writes the products (it reports ``WRITING_PRODUCTS`` itself).

``run_slam(log, config)`` feeds every message of the log to a :class:`SlamFilter` and collects a
:class:`SlamResult`: the best particle's trajectory and the dead-reckoning trajectory (one pose per
scan), the best particle's final map, per-scan statistics, snapshots, wall time and peak memory.
A caller that steps a filter itself (messages that arrive over time) collects the same result with
:func:`filter_result` once the filter has seen the whole log.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from slam_engine.backend.flagged_retry import FlaggedRetry, kept_alternative, retry_alternatives
from slam_engine.backend.map_alignment import align_to_map
from slam_engine.backend.map_builder import render_occupancy, render_with_frames
from slam_engine.backend.odometry_smoothing import smooth_with_odometry
from slam_engine.backend.pose_graph import Edge
from slam_engine.backend.submap_choice import CheckedLoopClosing, close_loops_checked
from slam_engine.config import LoopClosingConfig, SlamConfig
from slam_engine.errors import ConfigError
from slam_engine.evaluation.consistency import MapConsistency, map_consistency
from slam_engine.evaluation.memory_estimate import peak_resident_bytes
from slam_engine.frontend.lidar_points import ProjectedScan
from slam_engine.frontend.odometry import dead_reckoning, odometry_source
from slam_engine.frontend.odometry_noise import estimate_noise
from slam_engine.frontend.open_ground import open_ground_config
from slam_engine.frontend.particle_filter import SlamFilter, engine_threads
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.messages import ScanMessage
from slam_engine.model.result import (
    MapSnapshot,
    OccupancyGrid,
    ScanStats,
    SlamResult,
    TextureMap,
    Trajectory,
)
from slam_engine.progress import (  # re-exported: callers of run_slam find them here
    ALIGNING_TO_MAP,
    CLOSING_LOOPS,
    MAPPING_SCANS,
    RENDERING_MAP,
    STAGE_SHARES,
    STAGES,
    WRITING_PRODUCTS,
    ProgressCallback,
    RunProgress,
    run_fraction,
    stage_progress,
)

__all__ = ["ALIGNING_TO_MAP", "CLOSING_LOOPS", "MAPPING_SCANS", "RENDERING_MAP", "STAGES", "STAGE_SHARES",
           "WRITING_PRODUCTS", "ProgressCallback", "RunProgress", "filter_result", "map_bundle", "run_fraction",
           "run_filter", "run_slam", "stage_progress"]

def _peak_rss_bytes() -> int:
    """Peak resident memory of this process so far [bytes] (:func:`peak_resident_bytes`)."""
    return peak_resident_bytes()


def _return_freed_memory() -> None:
    """Give the pages of freed heap memory back to the system (glibc's ``malloc_trim``): the maps and
    temporaries of one phase, freed in the middle of the heap, would otherwise stay resident while
    the next phase allocates anew. Nothing where the C library has no such call."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.cache
def _malloc_trim():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def _empty_stats() -> ScanStats:
    empty = np.zeros(0)
    return ScanStats(t_s=empty, n_eff=empty, resampled=np.zeros(0, bool), match_score=empty,
                     matched=np.zeros(0, bool), step_time_s=empty)


def run_slam(log: DriveLog, config: SlamConfig | None = None, rng: np.random.Generator | None = None,
             progress: ProgressCallback | None = None, live_previews: bool | None = None) -> SlamResult:
    """Run RBPF SLAM over ``log``.

    ``rng`` defaults to ``numpy.random.default_rng(config.seed)`` (same seed, same map).
    ``progress`` is called after every scan with a :class:`RunProgress`; raising
    :class:`~slam_engine.errors.Cancelled` from it stops the run. ``live_previews`` (default: when
    there is a ``progress``): its newest snapshot is at preview size; without, snapshots are kept at
    an animation frame's size from the start (the same frames, less memory). A log without odometry
    raises :class:`ConfigError`; a log without scans gives a dead-reckoning-only result with a warning."""
    config = SlamConfig() if config is None else config
    start = time.perf_counter()
    odometry_source(log)  # ConfigError when there is none
    rng = np.random.default_rng(config.seed) if rng is None else rng
    scans_total = 0 if log.scans is None else len(log.scans)
    if log.scans is None or scans_total == 0 or log.lidar is None:
        dr = dead_reckoning(log)
        warnings = [*log.warnings, "the log has no LiDAR scans: the result is dead reckoning only, with an empty map"]
        return SlamResult(
            trajectory=dr, dead_reckoning=dr,
            grid=OccupancyGrid(np.zeros((1, 1), np.float32), config.grid.resolution_m, 0.0, 0.0),
            scan_stats=_empty_stats(), config=config, wall_time_s=time.perf_counter() - start,
            peak_memory_bytes=_peak_rss_bytes(), warnings=warnings, input_summary=log.summary())
    if log.lidar.num_beams != log.scans.ranges_m.shape[1]:
        raise ConfigError(f"the LiDAR model has {log.lidar.num_beams} beams but the scans have "
                          f"{log.scans.ranges_m.shape[1]} ranges")

    config, open_ground = open_ground_config(config, log)
    slam = run_filter(log, config, rng, progress, start, live_previews)
    if progress is not None:
        progress(RunProgress(scans_total, scans_total, time.perf_counter() - start))
    result = filter_result(slam, log, config, start, progress)
    result.input_summary["open_ground"] = open_ground
    del slam
    _return_freed_memory()
    return result


def run_filter(log: DriveLog, config: SlamConfig, rng: np.random.Generator, progress: ProgressCallback | None = None,
               started_s: float | None = None, live_previews: bool | None = None) -> SlamFilter:
    """The front end alone: a :class:`SlamFilter` stepped through every odometry and scan message of
    ``log`` (which has scans and a LiDAR model) and finished, before the back end
    (:func:`filter_result`). ``progress`` and ``live_previews`` as in :func:`run_slam`, timed from
    ``started_s``."""
    started_s = time.perf_counter() if started_s is None else started_s
    scans_total = 0 if log.scans is None else len(log.scans)
    slam = SlamFilter.from_log(log, config, rng)
    slam.live_previews = progress is not None if live_previews is None else live_previews
    odometry_only = DriveLog(vehicle=log.vehicle, encoders=log.encoders, gyro=log.gyro, odometry=log.odometry,
                             scans=log.scans)
    for message in odometry_only.messages():
        slam.step(message)
        if progress is not None and isinstance(message, ScanMessage):
            progress(RunProgress(slam.scans_seen, scans_total, time.perf_counter() - started_s,
                                 slam.snapshots[-1] if slam.snapshots else None))
    slam.finish()
    return slam


def filter_result(slam: SlamFilter, log: DriveLog, config: SlamConfig, started_s: float,
                  progress: ProgressCallback | None = None) -> SlamResult:
    """The :class:`SlamResult` of a filter that has stepped through every message of ``log`` (in
    time order) and been finished: what :func:`run_slam` returns, also for a caller that fed the
    filter itself, message by message as they arrived. Only the best particle's map is kept in the
    filter afterwards (the others are freed): it is not stepped further. ``started_s`` is the run's
    ``time.perf_counter()`` at its start (for the wall time). ``progress`` hears the back end's stages
    (:data:`CLOSING_LOOPS` with its share of key frames searched, :data:`ALIGNING_TO_MAP`,
    :data:`RENDERING_MAP`)."""
    scans_total = 0 if log.scans is None else len(log.scans)

    def report(stage: str, stage_fraction: float = 0.0) -> None:
        if progress is not None:
            progress(stage_progress(stage, scans_total, started_s, stage_fraction))

    report(CLOSING_LOOPS)
    warnings = list(log.warnings)
    grid_memory_bytes = slam.grids.memory_bytes()
    # from here on only the best particle's map is read: the others' tiles are freed before the back end
    slam.grids.keep_only(slam.best_particle())
    _return_freed_memory()
    front_end_path = slam.key_frame_path()
    key_frame_points = [scan.hits_v for scan in slam.key_frame_scans]
    unverified = ~slam.key_frame_matched()

    def back_end(loop_config: LoopClosingConfig, reported: bool = False) -> _BackEnd:
        return _close_loops_and_align(
            front_end_path, key_frame_points, unverified, loop_config, slam, config,
            progress=(lambda done: report(CLOSING_LOOPS, done)) if reported else None,
            aligning=(lambda: report(ALIGNING_TO_MAP)) if reported else None)

    run = back_end(config.loop_closing, reported=True)
    _return_freed_memory()
    report(RENDERING_MAP)
    resampled = slam.scan_stats().resampled
    if len(resampled) > 1 and resampled.mean() > 0.9:
        warnings.append("the particle set was resampled after almost every scan: the map may be unreliable "
                        "(odometry much worse than the motion noise assumes?)")
    # the particles' maps hold only their recent tiles when local_map_m is set: re-rendered then too
    rerender = (any(c.accepted for c in run.checked.backend.closures) or config.grid.no_return_bounded
                or run.smoothing.get("applied") or run.alignment.get("applied") or config.matcher.local_map_m > 0)
    grid, snapshots = _product_map(slam, run.key_frames, run.trajectory, config, rerender)
    consistency = map_consistency(grid, run.key_frames, key_frame_points)
    retry = None
    if consistency.flagged:
        retry, kept = _retry_flagged(consistency, run, back_end, slam, key_frame_points, config)
        if kept is not None:
            run = kept
            grid, snapshots = _product_map(slam, run.key_frames, run.trajectory, config, rerender=True)
            consistency = map_consistency(grid, run.key_frames, key_frame_points)
    if (inconsistent := consistency.warning()) is not None:
        warnings.append(inconsistent)
    key_frames, trajectory, backend, checked = run.key_frames, run.trajectory, run.checked.backend, run.checked
    loop_summary = {**_with_places(backend.summary(), key_frames), **checked.summary()}
    if retry is not None:
        loop_summary["flagged_retry"] = retry.summary()
    texture, texture_status = _ground_texture(log, trajectory, grid, config, warnings)
    bundle = map_bundle(key_frames, slam.key_frame_times(), ~slam.key_frame_matched(), slam.product_scans(),
                        slam.projector.origin_v, backend.edges, trajectory, config, log)
    report(RENDERING_MAP, 1.0)
    return SlamResult(
        trajectory=trajectory,
        dead_reckoning=dead_reckoning(log),
        grid=grid,
        texture=texture,
        scan_stats=slam.scan_stats(),
        config=config,
        snapshots=snapshots,
        wall_time_s=time.perf_counter() - started_s,
        peak_memory_bytes=_peak_rss_bytes(),
        warnings=warnings,
        input_summary={**log.summary(), "grid_memory_bytes": grid_memory_bytes,
                       "scans_processed": slam.steps_processed, "texture": texture_status,
                       "odometry_calibration": slam.heading_calibration.summary(),
                       "odometry_precision": slam.odometry_precision.summary(),
                       "time_offset": _time_offset_summary(slam, log, config),
                       "loop_closing": loop_summary, "map_alignment": run.alignment,
                       "odometry_smoothing": run.smoothing, "map_consistency": consistency.as_dict()},
        bundle=bundle,
    )


@dataclass
class _BackEnd:
    """One pass of the back end over the front end's key frames: the loop closing (with its step
    check), the key frames aligned to the map and smoothed with the odometry, and every scan's pose."""

    checked: CheckedLoopClosing
    key_frames: np.ndarray
    alignment: dict
    smoothing: dict
    trajectory: Trajectory


def _close_loops_and_align(front_end_path: np.ndarray, points_v: list[np.ndarray], unverified: np.ndarray,
                           loop_config: LoopClosingConfig, slam: SlamFilter, config: SlamConfig,
                           progress: Callable[[float], None] | None = None,
                           aligning: Callable[[], None] | None = None) -> _BackEnd:
    """The back end with ``loop_config`` on the front end's key frames (``front_end_path`` (K, 3),
    their end points ``points_v`` [m, vehicle frame], the steps the front end left ``unverified``).
    ``progress`` hears the loop closing's share done, ``aligning`` when the alignment starts."""
    checked = close_loops_checked(front_end_path, points_v, loop_config, config.grid, unverified=unverified,
                                  threads=engine_threads(), progress=progress,
                                  places=config.place_index.for_far_searches())
    if aligning is not None:
        aligning()
    aligned, alignment = checked.backend.poses, {"applied": False, "reason": "loop closing is disabled"}
    if loop_config.enabled:
        aligned, alignment = align_to_map(checked.backend.poses, points_v, config.grid.resolution_m,
                                          loop_config.map_alignment_passes, loop_config.match_range_m)
    key_frames, smoothing = _keep_odometry_precision(aligned, slam.key_frame_odometry, slam.key_frame_wheels,
                                                     config)
    return _BackEnd(checked, key_frames, alignment, smoothing, slam.trajectory(key_frames))


def _retry_flagged(consistency: MapConsistency, first: _BackEnd, back_end: Callable[..., _BackEnd],
                   slam: SlamFilter, points_v: list[np.ndarray], config: SlamConfig
                   ) -> tuple[FlaggedRetry, _BackEnd | None]:
    """The back end again with each of :func:`retry_alternatives` of a map its own key frames flag
    (``consistency``), each alternative's map judged the same way; the alternative kept
    (:func:`kept_alternative`), or None (:mod:`slam_engine.backend.flagged_retry`)."""
    retry = FlaggedRetry(consistency.contradicted_share)
    runs = []
    for name, loop_config in retry_alternatives(config.loop_closing, first.checked):
        run = back_end(loop_config)
        grid = render_occupancy(slam.product_scans(), run.key_frames, slam.projector.origin_v, config.grid)
        retry.tried.append((name, map_consistency(grid, run.key_frames, points_v).contradicted_share))
        runs.append(run)
        del grid
        _return_freed_memory()
    if not runs:
        retry.reason = ("the submap lengths were all tried already (submap_lengths_tried)" if first.checked.tried
                        else "no alternative: loop closing is off")
        return retry, None
    kept = kept_alternative(retry.first_share, [share for _, share in retry.tried])
    if kept is None:
        return retry, None
    retry.kept = retry.tried[kept][0]
    return retry, runs[kept]


def _product_map(slam: SlamFilter, key_frames: np.ndarray, trajectory: Trajectory, config: SlamConfig,
                 rerender: bool) -> tuple[OccupancyGrid, list[MapSnapshot]]:
    """The product map at the final ``key_frames`` (K, 3) and the animation's frames: rendered from the
    key frames' scans where ``rerender`` or the filter marked frames, else the best particle's own."""
    if rerender or slam.frame_marks:
        # the poses are the best particle's when not re-rendered: its own map is then the same grid
        own_map = None if rerender else slam.best_grid()
        slam.grids.keep_only(None)  # no particle's map is read any more
        _return_freed_memory()
        marks = slam.frame_marks or [(s.scan_index, s.t_s) for s in slam.snapshots]
        # how many key frames each frame's map takes: those at or before its time
        key_frames_in = np.searchsorted(slam.key_frame_times(), [t_s for _, t_s in marks], side="right").tolist()
        grid, frames = render_with_frames(slam.product_scans(), key_frames, slam.projector.origin_v, config.grid,
                                          set(key_frames_in))
        grid = grid if own_map is None else own_map
        snapshots = [MapSnapshot(scan_index, t_s, frames[n], trajectory.until(t_s))
                     for (scan_index, t_s), n in zip(marks, key_frames_in, strict=True) if n in frames]
        return grid, snapshots
    # live: the snapshots taken during the filter are the map being built
    return slam.best_grid(), [s.reduced() for s in slam.snapshots]


def _with_places(loop_summary: dict, key_frames: np.ndarray) -> dict:
    """The loop-closing summary with each closure's two key frames placed on the final map:
    ``node_xy_m`` and ``anchor_xy_m`` [m, map frame] (what a viewer draws a closure between)."""
    for closure in loop_summary["closures"]:
        for end in ("node", "anchor"):
            closure[f"{end}_xy_m"] = [round(float(v), 4) for v in key_frames[closure[end], :2]]
    return loop_summary


def map_bundle(poses: np.ndarray, t_s: np.ndarray, unverified: np.ndarray, scans: Sequence[ProjectedScan],
               origin_v: np.ndarray, edges: list[Edge], trajectory: Trajectory, config: SlamConfig,
               log: DriveLog | None = None, drive: int = 0) -> MapBundle:
    """The :class:`MapBundle` of one drive: its key frames at their final ``poses`` (K, 3, map frame) and
    times ``t_s``, their product ``scans`` (a sequence that projects each when read: packed as they come),
    the pose graph's ``edges`` and every scan's pose."""
    offsets, ends_v, is_hit, free_from = MapBundle.pack_scans(scans)
    n_edges = len(edges)
    unverified = np.array(unverified, bool)
    unverified[:1] = True  # a drive's first key frame: nothing ties it to what came before
    lidar = None if log is None else log.lidar
    sensors = {} if lidar is None else {"lidar": {
        "name": lidar.name, "num_beams": lidar.num_beams, "angle_min_rad": lidar.angle_min_rad,
        "angle_increment_rad": lidar.angle_increment_rad, "range_min_m": lidar.range_min_m,
        "range_max_m": lidar.range_max_m, "T_vehicle_from_lidar": np.asarray(lidar.T_vehicle_from_lidar).tolist()}}
    bundle = MapBundle(
        poses=np.asarray(poses, np.float64), t_s=np.asarray(t_s, np.float64),
        drive=np.full(len(poses), drive, np.int32),
        unverified=unverified, scan_offsets=offsets, ends_v=ends_v, is_hit=is_hit, free_from_m=free_from,
        origin_v=np.asarray(origin_v, np.float64),
        edges_ij=np.array([(e.i, e.j) for e in edges], np.int64).reshape(n_edges, 2),
        edges_T_i_from_j=np.array([e.T_i_from_j for e in edges], np.float64).reshape(n_edges, 3),
        edges_sigmas=np.array([e.sigmas for e in edges], np.float64).reshape(n_edges, 3),
        edges_robust=np.array([e.robust for e in edges], bool),
        trajectory_t_s=np.asarray(trajectory.t_s, np.float64), trajectory=np.asarray(trajectory.poses, np.float64),
        trajectory_drive=np.full(len(trajectory), drive, np.int32), resolution_m=config.grid.resolution_m,
        config=config.model_dump(mode="json"), sensors=sensors)
    if len(bundle):  # its place index, kept with it: which of several saved maps a drive is in asks every one
        from slam_engine.multisession.localization import map_places_of

        bundle.places = map_places_of(bundle, config.place_index).stored(config.place_index.spacing_m)
    return bundle


def _keep_odometry_precision(poses: np.ndarray, odometry: list[np.ndarray], wheels: list[np.ndarray | None],
                             config: SlamConfig) -> tuple[np.ndarray, dict]:
    """The key-frame ``poses`` (the back end's, aligned to the map) smoothed with the odometry where the
    log shows that its odometry is locally more precise than they are, measured on them
    (:mod:`slam_engine.backend.odometry_smoothing`: the simulated car's local error 0.0036 m measured
    on the front end's path, 0.0019 m on the aligned poses), and a summary for run.json. ``wheels``:
    each key frame's wheel and gyro readings (None without both)."""
    if not config.loop_closing.odometry_smoothing:
        return poses, {"applied": False, "reason": "disabled in the configuration"}
    noise = estimate_noise(poses, np.asarray(odometry), wheels)
    if noise is None:
        return poses, {"applied": False, "reason": "too few key frames to measure the noise"}
    if not noise.odometry_helps:
        return poses, {"applied": False, "reason": "odometry is not more precise than the matches",
                       **noise.summary()}
    return smooth_with_odometry(poses, np.asarray(odometry), noise), {"applied": True, **noise.summary()}


def _time_offset_summary(slam: SlamFilter, log: DriveLog, config: SlamConfig) -> dict:
    """The time offset's estimate and use, and the de-skew: on (the LiDAR model gives its beams'
    timing and ``odometry.deskew``), the sweep [s] and how many key frames moved during it."""
    increment = None if log.lidar is None else log.lidar.time_increment_s
    on = bool(config.odometry.deskew and increment)
    return {**slam.time_offset.summary(), "deskew": on,
            "sweep_s": round(abs(increment) * (log.lidar.num_beams - 1), 5)
            if on and increment is not None and log.lidar else None,
            "deskewed_key_frames": sum(p is not None for p in slam.key_frame_sweeps)}


def _ground_texture(log: DriveLog, trajectory: Trajectory, grid: OccupancyGrid, config: SlamConfig,
                    warnings: list[str]) -> tuple[TextureMap | None, str]:
    """The ground texture on ``grid``'s cells once the trajectory is known, and a one-line status."""
    from slam_engine.texture import build_texture_map

    if log.stereo is None and log.rgbd is None:
        return None, "no texture: the log has no camera data"
    if not config.texture.enabled:
        return None, "no texture: disabled in the configuration"
    texture = build_texture_map(log, trajectory, grid, config, warnings=warnings)
    if texture is None:
        return None, "no texture: no camera frame could be used (see warnings)"
    return texture, f"texture from {int((texture.counts > 0).sum())} observed cells"
