"""The back end alone, re-run on a recorded front end: back-end experiments in seconds, not minutes.

The particle filter is most of a run's time (the corridor: about 35 of 45 s), and a change to loop
closing does not change it. ``record`` runs the filter once per seed, exactly as
:func:`slam_engine.pipeline.run_slam` does, and keeps what the back end reads: the best particle's
key-frame path, the key frames' end points and odometry, and their times. ``replay`` runs
:func:`slam_engine.backend.loop_closer.close_loops` on each recording with any ``loop_closing``
settings and scores the key frames against the benchmark's relations (for the scans that are key
frames; on the sparse logs that is every scan).

``python -m bench.backend_replay record --log corridor --seeds 0-4 --out /tmp/fe``
``python -m bench.backend_replay replay /tmp/fe [--set loop_closing.cauchy_scale=3]``

Where the log has ground truth (``NAME.gt.txt``), each row also lists the accepted closures whose
matched relation is off the truth's (false closures: the corridor's aliases; a heading closure by its
heading alone).

Logs: the benchmark names of :mod:`bench.engine_profile` (``intel``, ``freiburg``, ``aces``,
``corridor``) or a path to a log with ``NAME.relations`` beside it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.cases import datasets_root
from bench.engine_profile import BENCHMARK, overrides_from_pairs
from bench.options import parse_seeds

if TYPE_CHECKING:
    from slam_engine.model.result import Trajectory

# an accepted closure this far from the ground truth's relation is counted as false [m, rad]
FALSE_CLOSURE_M = 0.4
FALSE_CLOSURE_RAD = 0.04


def _log_path(name: str) -> Path:
    return datasets_root() / BENCHMARK[name] if name in BENCHMARK else Path(name)


def record(name: str, seed: int, out_dir: Path, overrides: dict) -> Path:
    """Run the filter over log ``name`` with ``seed``; write ``<stem>_seed<k>.npz`` into ``out_dir``."""
    from slam_engine.config import SlamConfig
    from slam_engine.formats import load_log
    from slam_engine.frontend.open_ground import open_ground_config
    from slam_engine.pipeline import run_filter

    path = _log_path(name)
    log = load_log(path)
    # the front end of `lidarmap run`: a drive on open ground is mapped without no-return clearing
    config, _ = open_ground_config(SlamConfig.model_validate({**overrides, "seed": seed}), log)
    slam = run_filter(log, config, np.random.default_rng(config.seed))
    points = [scan.hits_v for scan in slam.key_frame_scans]
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{path.stem}_seed{seed}.npz"
    np.savez_compressed(target, log=str(path), seed=seed, config=config.model_dump_json(),
                        path=slam.key_frame_path(), matched=slam.key_frame_matched(),
                        odometry=np.asarray(slam.key_frame_odometry),
                        t_s=slam.key_frame_times(), counts=np.array([len(p) for p in points]),
                        points=np.concatenate(points) if points else np.zeros((0, 2)))
    return target


def replay(recording: Path, overrides: dict) -> dict:
    """The back end on one recording with the recorded configuration plus ``overrides``; its summary
    and, where the log has relations, the key frames' relation errors."""
    from slam_engine.backend.submap_choice import close_loops_checked
    from slam_engine.config import SlamConfig, merge_settings
    from slam_engine.evaluation.metrics import files_beside_log, read_ground_truth, read_relations, relation_errors
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.model.result import Trajectory

    data = np.load(recording)
    config = SlamConfig.model_validate_json(str(data["config"]))
    config = SlamConfig.model_validate(merge_settings(config.model_dump(), overrides))
    points = np.split(data["points"], np.cumsum(data["counts"])[:-1])
    started = time.perf_counter()
    unverified = ~data["matched"] if "matched" in data else None
    # as lidarmap run: the front end's steps checked, then loop closing with each submap length tried
    checked = close_loops_checked(data["path"], points, config.loop_closing, config.grid, unverified,
                                  threads=engine_threads())
    result = checked.backend
    row = {"recording": recording.name, "backend_s": round(time.perf_counter() - started, 2)}
    summary = {**result.summary(), **checked.summary()}
    summary.pop("closures")
    row.update({k: v for k, v in summary.items() if k != "closures_rejected"})
    relations, truth = files_beside_log(str(data["log"]))
    if relations is not None:
        errors = relation_errors(Trajectory(t_s=data["t_s"], poses=result.poses), read_relations(relations))
        row.update(trans_m=round(errors.all.trans_mean_m, 4), local_m=round(errors.local.trans_mean_m, 4),
                   loop_m=round(errors.loop.trans_mean_m, 4))
    if truth is not None:
        row["false_closures"] = false_closures(result.closures, data["t_s"], read_ground_truth(truth))
    return row


def false_closures(closures: list, key_frame_t_s: np.ndarray, truth: Trajectory, max_m: float = FALSE_CLOSURE_M,
                   max_rad: float = FALSE_CLOSURE_RAD) -> list[dict]:
    """Accepted closures whose matched pose of the key frame in its anchor's frame is more than
    ``max_m`` / ``max_rad`` off the ground truth's (a heading closure: in heading alone; key frames
    without a true pose are skipped)."""
    from slam_engine.evaluation.metrics import match_times
    from slam_engine.model.poses import relative, wrap_angle

    index = match_times(truth.t_s, key_frame_t_s)
    out = []
    for c in closures:
        if not c.accepted or index[c.anchor] < 0 or index[c.node] < 0:
            continue
        true_relation = relative(truth.poses[index[c.anchor]], truth.poses[index[c.node]])
        error = np.asarray(c.T_anchor_from_node) - true_relation
        off_m, off_rad = float(np.hypot(error[0], error[1])), abs(float(wrap_angle(error[2])))
        if c.kind == "heading":  # a heading closure fixes only the heading
            off_m = 0.0
        if off_m > max_m or off_rad > max_rad:
            out.append({"node": c.node, "anchor": c.anchor, "kind": c.kind, "off_m": round(off_m, 3),
                        "off_rad": round(off_rad, 4)})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.backend_replay", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("record", help="run the filter once per seed and keep what the back end reads")
    rec.add_argument("--log", required=True, help="intel, freiburg, aces, corridor or a log path")
    rec.add_argument("--seeds", default="0")
    rec.add_argument("--out", type=Path, required=True)
    rec.add_argument("--set", action="append", default=[], metavar="a.b=value", help="SlamConfig override")
    rep = commands.add_parser("replay", help="re-run the back end on recordings and score it")
    rep.add_argument("recordings", type=Path, help="a recording (.npz) or a folder of them")
    rep.add_argument("--set", action="append", default=[], metavar="a.b=value", help="SlamConfig override")
    args = parser.parse_args(argv)
    overrides = overrides_from_pairs(args.set)
    if args.command == "record":
        for seed in parse_seeds(args.seeds):
            started = time.perf_counter()
            target = record(args.log, seed, args.out, overrides)
            print(f"{target} ({time.perf_counter() - started:.1f} s)")
        return 0
    paths = sorted(args.recordings.glob("*.npz")) if args.recordings.is_dir() else [args.recordings]
    if not paths:
        print(f"no recordings (.npz) in {args.recordings}", file=sys.stderr)
        return 2
    rows = [replay(p, overrides) for p in paths]
    for row in rows:
        print(json.dumps(row))
    scored = [r["trans_m"] for r in rows if "trans_m" in r]
    if scored:
        print(f"relation error: median {statistics.median(scored):.4f} m, worst {max(scored):.4f} m "
              f"over {len(scored)} recordings")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
