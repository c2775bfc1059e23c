"""One benchmark run in its own process: load a log, run SLAM with one seed, score it, save the map.

``python -m bench.worker JOB.json RESULT.json``. The job names the case, seed, particle count,
config overrides, output folder and the loader / runner functions (``module:function``). The parent
measures this process's peak memory and whole wall time; here ``wall_s`` is the SLAM run alone (not
loading), ``products_s`` the writing of every product (``write_products``, as ``lidarmap run``
does: no animation unless the job's config asks for snapshots), so the two can be compared, and
``scoring_s`` the bench's own work after that (the parent's ``run_process_s`` leaves it out of the
process's wall).
"""

from __future__ import annotations

import importlib
import json
import math
import sys
import time

STARTED_S = time.perf_counter()  # before the heavy imports: import time is part of the process's cost

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

DEFAULT_LOADER = "slam_engine.formats:load_log"
DEFAULT_RUNNER = "slam_engine.pipeline:run_slam"


def resolve(dotted: str):
    """The object named ``module:attribute``."""
    module_name, _, attribute = dotted.partition(":")
    if not attribute:
        raise ValueError(f"expected 'module:function', got {dotted!r}")
    return getattr(importlib.import_module(module_name), attribute)


def finite_or_none(value):
    """JSON-safe numbers: NaN and inf become None, recursively."""
    if isinstance(value, dict):
        return {key: finite_or_none(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_none(item) for item in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def score(trajectory, relations, ground_truth) -> dict:
    """Relation metrics and ATE of one trajectory (None where there is nothing to score against)."""
    from slam_engine.evaluation.metrics import absolute_trajectory_error, relation_errors

    scores: dict = {"relations": None, "ate_m": None}
    if relations is not None:
        scores["relations"] = relation_errors(trajectory, relations).as_dict()
    if ground_truth is not None:
        try:
            scores["ate_m"] = absolute_trajectory_error(trajectory, ground_truth)
        except ValueError as exc:
            scores["ate_error"] = str(exc)
    return scores


def dead_reckoning_agreement(log, dead_reckoning, config) -> dict | None:
    """Half agreement of the scans placed with dead reckoning (the baseline for the SLAM map's)."""
    from bench.agreement import half_agreement, scan_endpoints_world

    if log.scans is None or log.lidar is None or not len(log.scans) or not len(dead_reckoning):
        return None
    endpoints = scan_endpoints_world(log, dead_reckoning, config.grid.max_range_m)
    return half_agreement(endpoints)


def run_job(job: dict) -> dict:
    """Run one (case, seed) job and return its JSON-ready record (see module docstring)."""
    from bench.agreement import map_quality
    from slam_engine.config import SlamConfig, merge_settings, shortcut_overrides
    from slam_engine.evaluation.memory_estimate import peak_resident_bytes
    from slam_engine.evaluation.metrics import align_rigid_2d, read_ground_truth, read_relations
    from slam_engine.model.result import Trajectory
    from slam_engine.products import write_products
    from slam_engine.products.rendering import occupancy_with_trajectories

    case, seed = job["case"], int(job["seed"])
    shortcuts = shortcut_overrides({"seed": seed, "particles": job.get("particles")})
    overrides = merge_settings(job.get("config") or {}, shortcuts)
    import_s = time.perf_counter() - STARTED_S
    started = time.perf_counter()
    log = resolve(job.get("loader") or DEFAULT_LOADER)(case["log_path"])
    load_s = time.perf_counter() - started
    config = SlamConfig.model_validate(overrides)
    relations = read_relations(case["relations_path"]) if case.get("relations_path") else None
    ground_truth = read_ground_truth(case["ground_truth_path"]) if case.get("ground_truth_path") else None

    run_slam = resolve(job.get("runner") or DEFAULT_RUNNER)
    peak_before_slam_mb = peak_resident_bytes() / 2**20  # this process's own (not ru_maxrss: see there)
    started = time.perf_counter()
    result = run_slam(log, config)
    wall_s = time.perf_counter() - started
    out_dir = Path(job["out_dir"])
    started = time.perf_counter()
    write_products(result, out_dir / f"{case['name']}_seed{seed}_products", log=log)
    products_done = time.perf_counter()
    products_s = products_done - started
    # what a user's `lidarmap run` peaks at: the scoring below (bench only) is not part of it
    peak_run_mb = peak_resident_bytes() / 2**20

    scans = len(log.scans) if log.scans is not None else 0
    span = log.time_span_s()
    duration_s = 0.0 if span is None else span[1] - span[0]
    processed = int(len(result.scan_stats.t_s)) if result.scan_stats is not None else None
    truth_in_map = None
    if ground_truth is not None and len(result.trajectory) >= 2:
        # Ground truth drawn over the map: rigidly aligned onto the estimate (its frame may differ).
        from slam_engine.evaluation.metrics import match_times

        index = match_times(result.trajectory.t_s, ground_truth.t_s)
        if int((index >= 0).sum()) >= 2:
            rotation, shift = align_rigid_2d(ground_truth.poses[index >= 0, :2],
                                             result.trajectory.poses[index[index >= 0], :2])
            heading = math.atan2(rotation[1, 0], rotation[0, 0])
            truth_in_map = Trajectory(ground_truth.t_s.copy(), np.column_stack(
                [ground_truth.poses[:, :2] @ rotation.T + shift, ground_truth.poses[:, 2] + heading]))
    png = out_dir / f"{case['name']}_seed{seed}.png"
    occupancy_with_trajectories(result.grid, result.trajectory, truth_in_map).save(png)
    record = {
        "case": case["name"], "log_path": case["log_path"], "scored": bool(case.get("relations_path")),
        "seed": seed, "particles": config.particles, "status": "ok",
        "scans": scans, "scans_processed": processed, "duration_s": duration_s,
        "import_s": import_s, "load_s": load_s, "wall_s": wall_s, "products_s": products_s,
        "products_share": products_s / wall_s if wall_s > 0 else None,
        "peak_before_slam_mb": peak_before_slam_mb, "peak_run_mb": peak_run_mb,
        "scans_per_s": scans / wall_s if wall_s > 0 else None,
        "realtime_factor": duration_s / wall_s if wall_s > 0 else None,
        "slam": score(result.trajectory, relations, ground_truth),
        "dead_reckoning": score(result.dead_reckoning, relations, ground_truth),
        "map": {**map_quality(result.grid, log, result.trajectory, config.grid.max_range_m),
                "contradicted_key_frames": (result.input_summary.get("map_consistency") or {}).get(
                    "key_frames_contradicted_share")},
        "dead_reckoning_map": dead_reckoning_agreement(log, result.dead_reckoning, config),
        "map_png": str(png),
        "warnings": list(result.warnings),
        # the back end tried again on a flagged map (slam_engine.backend.flagged_retry): None when not
        "flagged_retry": (result.input_summary.get("loop_closing") or {}).get("flagged_retry"),
        "config": config.model_dump(mode="json"),
    }
    # the bench's own work after the products (map PNG with the ground truth, scores): the parent
    # subtracts it from the process's wall to give what `lidarmap run` costs
    record["scoring_s"] = time.perf_counter() - products_done
    return finite_or_none(record)


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m bench.worker JOB.json RESULT.json", file=sys.stderr)
        return 2
    job = json.loads(Path(argv[0]).read_text())
    record = run_job(job)
    from slam_engine.evaluation.memory_estimate import peak_resident_bytes

    record["peak_process_mb"] = peak_resident_bytes() / 2**20  # the whole process, scoring included
    Path(argv[1]).write_text(json.dumps(record, indent=1))
    import gc

    gc.freeze()  # exits as `lidarmap run` does (lidarmap.cli.freeze_for_exit): no collections at teardown
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
