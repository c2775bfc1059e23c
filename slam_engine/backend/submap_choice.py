"""The back end as a run applies it: the front end's steps checked (:mod:`step_rematch`), then loops
closed (:func:`close_loops`), once per submap length tried, keeping the result whose map its own key
frames contradict least.

Outdoors the submap length decides which revisits close, and no one length suits every drive: on the
ten recorded campus front ends (2026-11-28) 8 m and 16 m submaps each gave the better map on about half
of the seeds, by up to 0.59 m of relation error. A result whose parts overlap offset or turned has
more of its key frames' returns where other scans saw free space
(:func:`~slam_engine.evaluation.consistency.map_consistency`, no ground truth needed): the smaller share
of contradicted key frames picked the better length on 7 of those 10 seeds, and the median / worst
went from 0.17 / 0.65 m (8 m alone) to 0.13 / 0.45 m.

Poses are ``[x_m, y_m, theta_rad]`` of the vehicle in the world frame; points (N, 2) [m] in the
vehicle frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from slam_engine.backend.loop_closer import LoopClosingResult, close_loops
from slam_engine.backend.map_builder import render_occupancy
from slam_engine.backend.step_rematch import StepRematch, rematch_steps
from slam_engine.config import GridConfig, LoopClosingConfig, PlaceIndexConfig
from slam_engine.evaluation.consistency import map_consistency
from slam_engine.frontend.lidar_points import ProjectedScan


@dataclass
class CheckedLoopClosing:
    """The steps' check, the loop closing kept, and each submap length tried with the share of key
    frames its map contradicts (empty when only the configured length was tried)."""

    rematched: StepRematch
    backend: LoopClosingResult
    submap_length_m: float
    tried: list[tuple[float, float]] = field(default_factory=list)

    def summary(self) -> dict:
        out = self.rematched.summary()
        if self.tried:
            out["submap_length_m"] = self.submap_length_m
            out["submap_lengths_tried"] = [{"submap_length_m": length, "key_frames_contradicted_share": round(share, 4)}
                                           for length, share in self.tried]
        return out


def submap_lengths(config: LoopClosingConfig) -> list[float]:
    """The configured submap length [m], then each alternative not equal to it (in order, once)."""
    lengths = [config.submap_length_m]
    for length in config.alternative_submap_lengths_m:
        if length not in lengths:
            lengths.append(length)
    return lengths


def key_frames_contradicted(poses: np.ndarray, points_v: Sequence[np.ndarray], grid: GridConfig) -> float:
    """The share of key frames (at ``poses``) whose returns ``points_v`` mostly fall where the map
    of those same returns holds free space (rays from the vehicle to each return)."""
    scans = [ProjectedScan(p, np.ones(len(p), bool), np.zeros(len(p))) for p in points_v]
    occupancy = render_occupancy(scans, poses, np.zeros(2), grid)
    return map_consistency(occupancy, poses, points_v).contradicted_share


def close_loops_checked(path: np.ndarray, points_v: list[np.ndarray], config: LoopClosingConfig,
                        grid: GridConfig, unverified: np.ndarray | None = None, threads: int = 1,
                        progress: Callable[[float], None] | None = None,
                        places: PlaceIndexConfig | None = None) -> CheckedLoopClosing:
    """:func:`rematch_steps` on the front end's key-frame ``path`` (K, 3), then :func:`close_loops`
    with each of :func:`submap_lengths`; with more than one, the result whose key frames contradict
    its map least is kept (the first of equal ones). ``progress`` hears the share of the work done;
    ``places`` as in :func:`close_loops`."""
    rematched = rematch_steps(path, points_v, config, grid.resolution_m, threads=threads, unverified=unverified)
    lengths = submap_lengths(config)

    def closed_with(i: int) -> LoopClosingResult:
        def report(done: float) -> None:
            if progress is not None:
                progress((i + done) / len(lengths))

        return close_loops(rematched.path, points_v, config.model_copy(update={"submap_length_m": lengths[i]}),
                           grid.resolution_m, unverified=unverified, threads=threads, progress=report, places=places)

    results = [closed_with(i) for i in range(len(lengths))]
    if len(lengths) == 1:
        return CheckedLoopClosing(rematched, results[0], lengths[0])
    tried = [(length, key_frames_contradicted(result.poses, points_v, grid))
             for length, result in zip(lengths, results, strict=True)]
    kept = min(range(len(lengths)), key=lambda i: tried[i][1])  # the first of equal shares
    return CheckedLoopClosing(rematched, results[kept], lengths[kept], tried)
