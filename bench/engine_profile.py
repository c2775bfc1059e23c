"""Engine speed and accuracy on a few logs, one process per (log, seed) so CPU time and peak memory
belong to that run alone.

``python -m bench.engine_profile --log intel --seeds 0-4 [--particles 30] [--set matcher.max_points=150]
[--heading-error 1.3,0.02]`` (the last distorts the odometry: :mod:`bench.odometry_bias`)

Logs: ``intel``, ``freiburg`` (relation errors against the benchmark ground truth), ``exp2``,
``malaga`` (maps only: half agreement, :mod:`bench.agreement`), ``sim:<rig>`` (simulated drive, ATE
against its exact ground truth, and the local relation error between consecutive scans, dead
reckoning's beside both); every run with its estimated LiDAR time offset. Prints one line per run
and a summary per log: median / worst accuracy, median CPU s (``time.process_time`` of the SLAM
run), median wall s, peak RSS MB.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench.cases import datasets_root
from bench.options import parse_seeds

BENCHMARK = {"intel": "benchmark/intel.clf", "freiburg": "benchmark/freiburg-079.clf",
             "aces": "benchmark/aces-rough.clf", "corridor": "benchmark/infinite-corridor-rough.clf"}
MAPS_ONLY = {"exp2": "breezyslam/exp2.dat", "malaga": "malaga/malaga-telecom-one-loop.clf"}


def overrides_from_pairs(pairs: list[str]) -> dict:
    """``a.b=value`` pairs -> nested dict (values parsed as JSON when possible)."""
    out: dict = {}
    for pair in pairs:
        key, _, raw = pair.partition("=")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def run_one(name: str, seed: int, particles: int, overrides: dict, heading_error: tuple[float, float] | None = None,
            ) -> dict:
    """One run in this process: the record printed as JSON by the child."""
    import numpy as np

    from slam_engine.config import SlamConfig
    from slam_engine.evaluation.metrics import absolute_trajectory_error, read_relations, relation_errors
    from slam_engine.pipeline import run_slam

    root = datasets_root()
    config = SlamConfig.model_validate({**overrides, "seed": seed, "particles": particles})
    record: dict = {"log": name, "seed": seed}
    if name.startswith("sim:"):
        from slam_engine.simulation import simulate

        drive = simulate(None, seed=0, rig=name[4:])
        log, truth = drive.log, drive.ground_truth
    else:
        from slam_engine.formats import load_log

        path = root / (BENCHMARK.get(name) or MAPS_ONLY.get(name) or name)
        log, truth = load_log(path), None
    if heading_error is not None:
        from bench.odometry_bias import with_heading_error

        log = with_heading_error(log, *heading_error)
        record["heading_error"] = list(heading_error)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    result = run_slam(log, config, rng=np.random.default_rng(seed))
    record["cpu_s"] = time.process_time() - cpu0
    record["wall_s"] = time.perf_counter() - wall0
    record["scans"] = len(log.scans)
    record["processed"] = int(result.input_summary.get("scans_processed", 0))
    if name in BENCHMARK:
        stem = root / BENCHMARK[name]
        rel = relation_errors(result.trajectory, read_relations(stem.with_suffix(".relations")))
        record["trans_m"], record["rot_deg"] = rel.all.trans_mean_m, rel.all.rot_mean_deg
        record["loop_rot_deg"] = rel.loop.rot_mean_deg
        record["local_m"], record["loop_m"] = rel.local.trans_mean_m, rel.loop.trans_mean_m
    if name in MAPS_ONLY:
        from bench.agreement import half_agreement, scan_endpoints_world

        record["half_agreement"] = half_agreement(scan_endpoints_world(log, result.trajectory,
                                                                       config.grid.max_range_m))["half_agreement"]
    record["time_offset_s"] = result.input_summary.get("time_offset", {}).get("estimated_s")
    if truth is not None:
        from slam_engine.evaluation.metrics import Relations
        from slam_engine.simulation import relations

        record["ate_m"] = absolute_trajectory_error(result.trajectory, truth)
        record["dr_ate_m"] = absolute_trajectory_error(result.dead_reckoning, truth)
        true_rel = relations(truth, np.random.default_rng(0))
        rel = Relations(t1_s=true_rel[:, 0], t2_s=true_rel[:, 1], motion=true_rel[:, 2:])
        record["local_m"] = relation_errors(result.trajectory, rel).local.trans_mean_m
        record["dr_local_m"] = relation_errors(result.dead_reckoning, rel).local.trans_mean_m
    from slam_engine.evaluation.memory_estimate import peak_resident_bytes

    record["peak_mb"] = peak_resident_bytes() / 2**20
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", action="append", required=True, help="intel, freiburg, exp2, malaga, sim:<rig>")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], help="config override a.b=value")
    parser.add_argument("--heading-error", default=None, metavar="SCALE[,DRIFT]",
                        help="distort the odometry: turns times SCALE plus DRIFT rad per metre (e.g. 1.3,0.02)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    heading_error = None
    if args.heading_error:
        parts = [float(v) for v in args.heading_error.split(",")]
        heading_error = (parts[0], parts[1] if len(parts) > 1 else 0.0)
    overrides = overrides_from_pairs(args.set)
    seeds = parse_seeds(args.seeds)
    if args.child:
        print(json.dumps(run_one(args.log[0], seeds[0], args.particles, overrides, heading_error)))
        return 0
    for name in args.log:
        records = []
        for seed in seeds:
            cmd = [sys.executable, "-m", "bench.engine_profile", "--child", "--log", name, "--seeds", str(seed),
                   "--particles", str(args.particles)] + [f"--set={s}" for s in args.set]
            if args.heading_error:
                cmd += ["--heading-error", args.heading_error]
            out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ, cwd=Path.cwd())
            if out.returncode != 0:
                print(f"{name} seed {seed}: FAILED\n{out.stderr[-2000:]}")
                continue
            rec = json.loads(out.stdout.strip().splitlines()[-1])
            records.append(rec)
            acc = ""
            if "trans_m" in rec:
                acc = (f"trans {rec['trans_m']:.4f} m rot {rec['rot_deg']:.3f} deg "
                       f"local {rec['local_m']:.4f} m loop {rec['loop_m']:.4f} m")
            if "ate_m" in rec:
                acc += (f" ATE {rec['ate_m']:.3f} m (odometry {rec['dr_ate_m']:.3f}) local {rec['local_m']:.4f} m "
                        f"(odometry {rec['dr_local_m']:.4f})")
            if rec.get("half_agreement") is not None:
                acc += f" half agreement {rec['half_agreement']:.3f}"
            if rec.get("time_offset_s") is not None:
                acc += f" time offset {rec['time_offset_s']:+.3f} s"
            print(f"{name} seed {seed}: {acc} cpu {rec['cpu_s']:.1f} s wall {rec['wall_s']:.1f} s "
                  f"peak {rec['peak_mb']:.0f} MB processed {rec['processed']}/{rec['scans']}", flush=True)
        if not records:
            continue
        line = f"== {name}: "
        for key in ("trans_m", "rot_deg", "ate_m", "local_m", "half_agreement"):
            vals = [r[key] for r in records if r.get(key) is not None]
            if vals:
                worst = min(vals) if key == "half_agreement" else max(vals)  # agreement: higher is better
                line += f"{key} median {statistics.median(vals):.4f} worst {worst:.4f}; "
        cpu = statistics.median(r["cpu_s"] for r in records)
        wall = statistics.median(r["wall_s"] for r in records)
        line += f"cpu median {cpu:.1f} s, wall median {wall:.1f} s, peak {max(r['peak_mb'] for r in records):.0f} MB"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
