"""The place index's retrieval at the true revisits of the benchmark logs (ground truth says where they are).

Each log is walked as the back end walks it: every ``QUERY_EVERY_M`` of travel the stretch of scans over
the last ``STRETCH_M`` (joined by the drive's own scan-matched odometry, in its last scan's frame) queries
an index of the map at least ``GAP_M`` of travel behind (places along the ground-truth path, the map's
end points at their ground-truth poses; rebuilt every ``REBUILD_M``). A query is a *true revisit* when a
place of that index lies within ``REVISIT_M`` of its ground-truth position; it is *retrieved* when one of
the top ``k`` candidates lies within ``HIT_M`` of it, at a heading within ``HIT_RAD``. Recall@k: the
retrieved share of the true revisits; precision@1: the share of the best candidates, over every query that
returned any, that are right (a query that is not a revisit has no right answer).

    python -m bench.place_recall [LOG.clf ...]   # default: intel, aces-rough, corridor, campus
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import numpy as np

from bench.cases import datasets_root
from slam_engine.backend.place_index import PlaceCandidate, PlaceIndex
from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import match_times, read_ground_truth
from slam_engine.formats import load_log
from slam_engine.model.poses import place_each, wrap_angle
from slam_engine.multisession.localization import DriveScans

DEFAULT_LOGS = ("intel", "aces-rough", "infinite-corridor-rough", "freiburg-campus-rough")
QUERY_EVERY_M, STRETCH_M, GAP_M, REBUILD_M = 2.0, 8.0, 60.0, 20.0
REVISIT_M, HIT_M, HIT_RAD = 2.0, 3.0, 0.3
QUERY_POINTS = 3000


@dataclass
class Recall:
    """One log's retrieval figures."""

    name: str
    queries: int
    revisits: int
    retrieved_at_1: int
    retrieved_at_k: int
    right_best: int
    answered: int
    query_ms: float

    def row(self, k: int) -> str:
        recall_1 = self.retrieved_at_1 / max(self.revisits, 1)
        recall_k = self.retrieved_at_k / max(self.revisits, 1)
        precision = self.right_best / max(self.answered, 1)
        return (f"| {self.name} | {self.queries} | {self.revisits} | {recall_1:.3f} | {recall_k:.3f} | "
                f"{precision:.3f} | {self.query_ms:.1f} |")


def _right(candidate: PlaceCandidate, truth_xy: np.ndarray, truth_theta: float) -> bool:
    """Whether a candidate is where the ground truth puts the query (HIT_M, HIT_RAD)."""
    return (math.hypot(*(candidate.centre_m - truth_xy)) <= HIT_M
            and abs(float(wrap_angle(candidate.heading_rad - truth_theta))) <= HIT_RAD)


def measure(log_name: str, k: int = 5, radius_m: float | None = None, spacing_m: float | None = None) -> Recall:
    """Recall@1, recall@k and precision@1 of the place index on one benchmark log (see the module)."""
    folder = datasets_root() / "benchmark"
    config = SlamConfig()
    radius_m = config.place_index.radius_m if radius_m is None else radius_m
    spacing_m = config.place_index.spacing_m if spacing_m is None else spacing_m
    log = load_log(folder / f"{log_name}.clf")
    truth = read_ground_truth(folder / f"{log_name}.gt.txt")
    drive = DriveScans.from_log(log, config)
    at = match_times(truth.t_s, drive.t_s, 0.05)
    scans = np.flatnonzero(at >= 0)
    gt = truth.poses[at[scans]]
    hits = [drive.hits[i] for i in scans.tolist()]
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(gt[:, :2], axis=0).T))])
    counts = np.array([len(h) for h in hits])
    world = place_each(gt, np.concatenate(hits), np.repeat(np.arange(len(hits)), counts))
    starts = np.concatenate([[0], np.cumsum(counts)])
    out = Recall(log_name, 0, 0, 0, 0, 0, 0, 0.0)
    index, built_until, last_query, times = None, -np.inf, -np.inf, []
    for j in range(len(scans)):
        if travel[j] - last_query < QUERY_EVERY_M or travel[j] < GAP_M + STRETCH_M:
            continue
        last_query = travel[j]
        until = travel[j] - GAP_M
        if index is None or until - built_until >= REBUILD_M:
            behind = int(np.searchsorted(travel, until))
            index = PlaceIndex.along(world[: starts[behind]], gt[:behind, :2], spacing_m, radius_m)
            built_until = until
        first = int(np.searchsorted(travel, travel[j] - STRETCH_M))
        cloud = drive.cloud(int(scans[first]), int(scans[j]), QUERY_POINTS)
        started = time.perf_counter()
        found = index.query(cloud, k)
        times.append(time.perf_counter() - started)
        out.queries += 1
        truth_xy, truth_theta = gt[j, :2], gt[j, 2]
        revisit = len(index) and float(np.min(np.hypot(*(index.centres - truth_xy).T))) <= REVISIT_M

        right = [_right(c, truth_xy, truth_theta) for c in found]
        if found:
            out.answered += 1
            out.right_best += right[0]
        if revisit:
            out.revisits += 1
            out.retrieved_at_1 += bool(found) and right[0]
            out.retrieved_at_k += any(right)
    out.query_ms = 1000.0 * float(np.median(times)) if times else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="*", default=list(DEFAULT_LOGS))
    parser.add_argument("-k", type=int, default=5)
    parser.add_argument("--radius", type=float, default=None)
    parser.add_argument("--spacing", type=float, default=None)
    args = parser.parse_args(argv)
    print(table([measure(name, args.k, args.radius, args.spacing) for name in args.logs], args.k))
    return 0


def table(rows: list[Recall], k: int) -> str:
    head = (f"| log | queries | true revisits | recall@1 | recall@{k} | precision@1 | query [ms] |\n"
            "|---|---|---|---|---|---|---|")
    return "\n".join([head] + [r.row(k) for r in rows])


if __name__ == "__main__":
    raise SystemExit(main())
