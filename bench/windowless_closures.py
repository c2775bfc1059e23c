"""Loop closures found without a window, tried on a recorded front end (the experiment that led to the
back end's far searches, ``loop_closing.far_search``; this one places stretches with the localiser).

The loop closer searches for a key frame's loop only within a window that grows with the drift since
the last closure (``loop_closing.max_window_m``). Outdoors (freiburg-campus-rough) the front end is
47-104 m off by the time the drive comes back, and no window reaches. This tries the other way: every
``--probe-every`` metres of travel, the next 10 m of key frames (at the front end's relative poses) are
placed by :func:`slam_engine.multisession.localization.localize` - whole-map branch and bound, two
stretches confirming - in the map of the key frames at least ``--min-gap`` metres of travel behind
them, at their current estimates. A placement becomes a closure in the loop closer's motion graph,
which is re-optimised; at the end the windowed loop closer runs once more from the corrected poses.
``--ideal`` adds instead a closure wherever the ground truth says the drive is back within 3 m of
where it was (every 2 m of such travel), with the truth's relative pose: the best any closure search
could give this front end.

``python -m bench.backend_replay record --log .../freiburg-campus-rough.clf --seeds 0 --out /tmp/fe``
``python -m bench.windowless_closures /tmp/fe/freiburg-campus-rough_seed0.npz``
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from slam_engine.backend.loop_closer import LoopCloser, close_loops
from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import (
    files_beside_log,
    match_times,
    read_ground_truth,
    read_relations,
    relation_errors,
)
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.poses import relative
from slam_engine.model.result import Trajectory
from slam_engine.multisession.localization import DriveScans, localize

STRETCH_M = 10.0  # travel of key frames placed at once (the localiser confirms with a second stretch)
REVISIT_M = 3.0  # --ideal: back within this of an earlier pose [m]
IDEAL_EVERY_M = 2.0  # --ideal: one closure every this much travel of a revisit [m]


class Recording:
    """A ``bench.backend_replay`` recording with its log's relations and ground truth."""

    def __init__(self, path: Path):
        data = np.load(path)
        self.config = SlamConfig.model_validate_json(str(data["config"]))
        self.points = np.split(data["points"], np.cumsum(data["counts"])[:-1])
        self.path, self.t_s = data["path"], data["t_s"]
        self.unverified = ~data["matched"]
        relations, truth = files_beside_log(str(data["log"]))
        if relations is None or truth is None:
            raise SystemExit(f"{path}: its log needs NAME.relations and ground truth beside it")
        self.relations = read_relations(relations)
        self.truth = read_ground_truth(truth)
        self.truth_index = match_times(self.truth.t_s, self.t_s)  # -1: no true pose

    def error(self, poses: np.ndarray) -> dict:
        e = relation_errors(Trajectory(t_s=self.t_s, poses=poses), self.relations)
        return {"trans_m": round(e.all.trans_mean_m, 4), "local_m": round(e.local.trans_mean_m, 4),
                "loop_m": round(e.loop.trans_mean_m, 4)}

    def true_relation(self, a: int, b: int) -> np.ndarray | None:
        ia, ib = self.truth_index[a], self.truth_index[b]
        return None if ia < 0 or ib < 0 else relative(self.truth.poses[ia], self.truth.poses[ib])

    def bundle(self, poses: np.ndarray, keys: np.ndarray) -> MapBundle:
        """Key frames ``keys`` at ``poses[keys]`` as a map to localise in (their returns only)."""
        points = [self.points[k] for k in keys]
        ends = np.concatenate(points).astype(np.float32)
        n = len(keys)
        return MapBundle(poses=poses[keys].copy(), t_s=self.t_s[keys].copy(), drive=np.zeros(n, np.int64),
                         unverified=np.zeros(n, bool),
                         scan_offsets=np.r_[0, np.cumsum([len(p) for p in points])].astype(np.int64),
                         ends_v=ends, is_hit=np.ones(len(ends), bool), free_from_m=np.zeros(len(ends), np.float32),
                         origin_v=np.zeros(2), edges_ij=np.zeros((0, 2), np.int64), edges_T_i_from_j=np.zeros((0, 3)),
                         edges_sigmas=np.zeros((0, 3)), edges_robust=np.zeros(0, bool),
                         trajectory_t_s=self.t_s[keys].copy(), trajectory=poses[keys].copy(),
                         trajectory_drive=np.zeros(n, np.int64), resolution_m=self.config.grid.resolution_m)


def searched_closures(rec: Recording, closer: LoopCloser, probe_every_m: float, min_gap_m: float,
                      threads: int) -> tuple[np.ndarray, list[dict], int]:
    """The motion graph with closures found by placing stretches in the map behind them; the
    optimised poses, the closures (with how far each is off the truth's relation) and the searches."""
    graph, travel = closer.graph, closer.travel_m
    c = rec.config.loop_closing
    sigmas = np.array([c.closure_sd_m, c.closure_sd_m, c.closure_sd_rad])
    est = rec.path.copy()
    closures: list[dict] = []
    searches, last_probe_m = 0, -np.inf
    for k in range(len(est)):
        behind = np.flatnonzero(travel < travel[k] - min_gap_m)
        end = min(int(np.searchsorted(travel, travel[k] + STRETCH_M)), len(est) - 1)
        if travel[k] - last_probe_m < probe_every_m or len(behind) < 20 or end - k < 3:
            continue
        last_probe_m = travel[k]
        drive = DriveScans(rec.t_s[k:end + 1].copy(), rec.path[k:end + 1].copy(), rec.points[k:end + 1])
        placed = localize(rec.bundle(est, behind), drive, rec.config, threads=threads)
        searches += 1
        tracked = np.flatnonzero(placed.tracked)
        if not placed.localised or placed.trajectory is None or not len(tracked):
            continue
        node, pose = k + int(tracked[0]), placed.trajectory.poses[int(tracked[0])]
        anchor = int(behind[np.argmin(np.hypot(*(est[behind, :2] - pose[:2]).T))])
        found = relative(est[anchor], pose)
        truth = rec.true_relation(anchor, node)
        closures.append({"node": node, "anchor": anchor, "travel_m": round(float(travel[node]), 1),
                         "correction_m": round(float(np.hypot(*(pose[:2] - est[node, :2]))), 2),
                         "off_truth_m": None if truth is None else round(float(np.hypot(*(found - truth)[:2])), 3)})
        graph.add_edge(anchor, node, found, sigmas, robust=True)
        est = graph.optimize(est, robust=False)
    return graph.optimize(graph.optimize(est, robust=False)), closures, searches


def ideal_closures(rec: Recording, closer: LoopCloser, min_gap_m: float) -> tuple[np.ndarray, int]:
    """The motion graph with a closure at every revisit, its relative pose the truth's."""
    c = rec.config.loop_closing
    sigmas = np.array([c.closure_sd_m, c.closure_sd_m, c.closure_sd_rad])
    known = rec.truth_index >= 0
    true_xy = rec.truth.poses[np.maximum(rec.truth_index, 0), :2]  # read only where known
    true_travel = np.zeros(len(known))  # along the true poses of the key frames that have one
    true_travel[known] = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(true_xy[known], axis=0).T))])
    added, last_m = 0, -np.inf
    for k in np.flatnonzero(known):
        behind = np.flatnonzero(known & (true_travel < true_travel[k] - min_gap_m))
        if true_travel[k] - last_m < IDEAL_EVERY_M or not len(behind):
            continue
        distance = np.hypot(*(true_xy[behind] - true_xy[k]).T)
        if distance.min() > REVISIT_M:
            continue
        anchor = int(behind[np.argmin(distance)])
        truth = rec.true_relation(anchor, int(k))
        assert truth is not None  # both key frames have a true pose
        closer.graph.add_edge(anchor, int(k), truth, sigmas, robust=True)
        added, last_m = added + 1, true_travel[k]
    return closer.graph.optimize(closer.graph.optimize(rec.path.copy(), robust=False)), added


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.windowless_closures", description=__doc__.split("\n")[0])
    parser.add_argument("recording", type=Path, help="a bench.backend_replay recording (.npz)")
    parser.add_argument("--probe-every", type=float, default=10.0, help="travel between searches [m]")
    parser.add_argument("--min-gap", type=float, default=60.0, help="travel behind a stretch its map starts at [m]")
    parser.add_argument("--ideal", action="store_true", help="closures from the ground truth instead of searches")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    rec = Recording(args.recording)
    c = rec.config.loop_closing
    closer = LoopCloser(rec.path, rec.points, c, rec.config.grid.resolution_m, rec.unverified)
    row: dict = {"recording": args.recording.name, "front_end": rec.error(rec.path)}
    started = time.perf_counter()
    if args.ideal:
        poses, row["ideal_closures"] = ideal_closures(rec, closer, args.min_gap)
    else:
        poses, closures, row["searches"] = searched_closures(rec, closer, args.probe_every, args.min_gap, args.threads)
        row["closures"] = closures
    row["search_s"] = round(time.perf_counter() - started, 1)
    row["with_closures"] = rec.error(poses)
    windowed = close_loops(poses, rec.points, c, rec.config.grid.resolution_m, rec.unverified, threads=args.threads)
    row["then_windowed"] = {**rec.error(windowed.poses), "closures": sum(cl.accepted for cl in windowed.closures)}
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
