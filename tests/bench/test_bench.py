"""The benchmark harness on a tiny CARMEN log with a stand-in SLAM function: child processes, JSON
records, medians and worst seeds, dead-reckoning row, map numbers, PNGs and the printed tables."""

from __future__ import annotations

import json
import math
import textwrap

import numpy as np
import pytest
from PIL import Image
from rich.console import Console
from scipy import ndimage

from bench.agreement import half_agreement, occupied_with_neighbour, wall_thickness_m
from bench.cases import cases_for_path, simulated_cases
from bench.harness import BUSY_LOOP, BenchOptions, busy_processes, run_benchmark
from bench.options import parse_seeds
from bench.report import print_report
from slam_engine.evaluation.metrics import Relations, read_ground_truth, read_relations, relation_errors
from slam_engine.formats import load_log, write_log
from slam_engine.model.drive_log import DriveLog, LidarModel, MotionModelKind, OdometryStream, ScanStream, VehicleModel
from slam_engine.model.poses import relative
from slam_engine.model.result import OccupancyGrid, Trajectory

N_SCANS = 12
SCAN_PERIOD_S = 5.0  # 12 scans over 55 s: the first-to-last relation is a loop (> 30 s)

# Stand-in engine: its trajectory is the odometry with x stretched by 5 % per seed, its map one
# straight wall 40 cells long (0.1 m cells).
FAKE_ENGINE = textwrap.dedent('''
    import numpy as np
    from slam_engine.model.result import OccupancyGrid, ScanStats, SlamResult, Trajectory

    def run_slam(log, config, rng=None, progress=None):
        odometry = Trajectory(log.odometry.t_s.copy(), log.odometry.poses.copy())
        poses = odometry.poses.copy()
        poses[:, 0] *= 1.0 + 0.05 * config.seed
        log_odds = np.zeros((40, 40))
        log_odds[20, :] = 3.0
        n = len(log.scans)
        stats = ScanStats(log.scans.t_s, np.full(n, float(config.particles)), np.zeros(n, bool),
                          np.ones(n), np.ones(n, bool), np.zeros(n))
        return SlamResult(trajectory=Trajectory(odometry.t_s, poses), dead_reckoning=odometry,
                          grid=OccupancyGrid(log_odds, 0.1, -2.0, -2.0), scan_stats=stats, config=config)

    def broken(log, config, rng=None, progress=None):
        raise RuntimeError("stand-in engine failure")
''')


def ground_truth() -> Trajectory:
    t = 100.0 + SCAN_PERIOD_S * np.arange(N_SCANS)
    x = 0.3 * np.arange(N_SCANS)
    return Trajectory(t, np.column_stack([x, 0.1 * np.sin(x), 0.05 * np.arange(N_SCANS)]))


def write_case(folder, with_truth: bool = True):
    """A CARMEN log whose odometry drifts from the ground truth, with relations and ground truth."""
    truth = ground_truth()
    odometry = truth.poses.copy()
    odometry[:, 2] += 0.01 * np.arange(N_SCANS)  # heading drift
    odometry[:, 0] *= 1.02
    lidar = LidarModel(num_beams=181, angle_min_rad=-math.pi / 2, angle_increment_rad=math.pi / 180,
                       range_min_m=0.1, range_max_m=30.0)
    # A corridor: walls at y = +-1.5 m, ranges cast from the true poses.
    world_angle = truth.poses[:, 2:3] + lidar.beam_angles_rad
    wall_y = np.where(np.sin(world_angle) > 0, 1.5, -1.5)
    with np.errstate(divide="ignore"):
        ranges = ((wall_y - truth.poses[:, 1:2]) / np.sin(world_angle)).astype(np.float32)
    ranges[(ranges > 20.0) | ~np.isfinite(ranges)] = np.inf
    log = DriveLog(vehicle=VehicleModel(kind=MotionModelKind.ODOMETRY), lidar=lidar,
                   scans=ScanStream(truth.t_s.copy(), ranges), odometry=OdometryStream(truth.t_s.copy(), odometry))
    folder.mkdir()
    write_log(log, "carmen", folder)
    if with_truth:
        pairs = np.array([(k, k + 1) for k in range(N_SCANS - 1)] + [(0, N_SCANS - 1)])
        motion = relative(truth.poses[pairs[:, 0]], truth.poses[pairs[:, 1]])
        rows = np.column_stack([truth.t_s[pairs[:, 0]], truth.t_s[pairs[:, 1]], motion[:, :2],
                                np.zeros((len(pairs), 3)), motion[:, 2]])
        np.savetxt(folder / "log.relations", rows, fmt="%.9f")
        np.savetxt(folder / "ground_truth.txt", np.column_stack([truth.t_s, truth.poses]), fmt="%.9f")
    return folder


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    (root / "fake_engine.py").write_text(FAKE_ENGINE)
    cases = cases_for_path(write_case(root / "scored")) + cases_for_path(write_case(root / "maponly", False))
    options = BenchOptions(seeds=[0, 1, 2], particles=7, runner="fake_engine:run_slam",
                           extra_pythonpath=[str(root)], out_dir=root / "out")
    results = run_benchmark(cases[:1], options)
    options.seeds, options.out_dir = [3], root / "out_map"
    map_results = run_benchmark(cases[1:], options)
    options.runner, options.out_dir, options.busy = "fake_engine:broken", root / "out_broken", 1
    broken_results = run_benchmark(cases[:1], options)
    return root, results, map_results, broken_results


def expected_relation_errors(root, stretch: float, odometry: bool = False):
    log = load_log(root / "scored" / "log.clf")
    poses = log.odometry.poses.copy()
    if not odometry:
        poses[:, 0] *= stretch
    return relation_errors(Trajectory(log.odometry.t_s, poses), read_relations(root / "scored" / "log.relations"))


def test_cases_find_relations_and_ground_truth(tmp_path):
    case = cases_for_path(write_case(tmp_path / "c"))[0]
    assert case.name == "log" and case.scored
    assert case.relations_path.endswith("log.relations") and case.ground_truth_path.endswith("ground_truth.txt")


def test_json_records_every_seed_with_consistent_numbers(bench_run):
    root, results, _, _ = bench_run
    written = json.loads((root / "out" / "results.json").read_text())
    assert written["summaries"] == results["summaries"]
    assert len(written["code"]["commit"]) == 40 and written["machine"]["cpu_count"] >= 1
    runs = written["runs"]
    assert [r["seed"] for r in runs] == [0, 1, 2] and all(r["status"] == "ok" for r in runs)
    for run in runs:
        assert run["scans"] == N_SCANS and run["particles"] == 7 and run["config"]["particles"] == 7
        assert run["duration_s"] == pytest.approx(SCAN_PERIOD_S * (N_SCANS - 1), abs=1e-3)
        assert run["scans_per_s"] == pytest.approx(N_SCANS / run["wall_s"])
        assert run["realtime_factor"] == pytest.approx(run["duration_s"] / run["wall_s"])
        assert run["peak_memory_mb"] > 10  # a Python process with numpy: measured, not zero
        assert 10 < run["peak_before_slam_mb"] <= run["peak_run_mb"] <= run["peak_memory_mb"]
        expected = expected_relation_errors(root, 1.0 + 0.05 * run["seed"])
        assert run["slam"]["relations"]["all"]["trans_mean_m"] == pytest.approx(expected.trans_mean_m, abs=1e-5)
        assert run["slam"]["relations"]["all"]["n_relations"] == N_SCANS
        assert run["slam"]["relations"]["loop"]["n_relations"] == 1
        assert run["slam"]["ate_m"] >= 0
        with Image.open(run["map_png"]) as image:
            assert image.size == (40, 40)
        # the products, as `lidarmap run` writes them, timed apart from SLAM; the whole process too
        products = root / "out" / f"log_seed{run['seed']}_products"
        assert (products / "occupancy.png").exists() and (products / "run.json").exists()
        assert run["products_s"] > 0 and run["products_share"] == pytest.approx(run["products_s"] / run["wall_s"])
        assert run["process_s"] > run["import_s"] + run["load_s"] + run["wall_s"] + run["products_s"]
        # what `lidarmap run` costs: the process less the bench's scoring after the products
        assert 0 < run["scoring_s"] < run["process_s"]
        assert run["run_process_s"] == pytest.approx(run["process_s"] - run["scoring_s"])
        assert run["run_process_s"] > run["import_s"] + run["load_s"] + run["wall_s"] + run["products_s"]
        # no animation, as `lidarmap run` draws none unless asked for
        assert run["config"]["snapshot_every_scans"] == 0 and not (products / "animation.gif").exists()
    summary = written["summaries"][0]
    assert summary["products_s"] == sorted(r["products_s"] for r in runs)[1]  # median of 3
    assert summary["run_process_s"] == sorted(r["run_process_s"] for r in runs)[1]


def test_summary_takes_median_and_worst_seed(bench_run):
    root, results, _, _ = bench_run
    summary = results["summaries"][0]
    per_seed = [expected_relation_errors(root, 1.0 + 0.05 * s).trans_mean_m for s in (0, 1, 2)]
    assert summary["seeds_ok"] == 3 and summary["scans"] == N_SCANS
    assert summary["slam"]["trans_mean_m"]["median"] == pytest.approx(sorted(per_seed)[1], abs=1e-5)
    assert summary["slam"]["trans_mean_m"]["worst"] == pytest.approx(max(per_seed), abs=1e-5)
    assert summary["peak_memory_mb"] == max(r["peak_memory_mb"] for r in results["runs"])
    odometry = expected_relation_errors(root, 1.0, odometry=True)
    assert summary["dead_reckoning"]["trans_mean_m"] == pytest.approx(odometry.trans_mean_m, abs=1e-5)
    assert summary["dead_reckoning"]["rot_mean_deg"] == pytest.approx(odometry.rot_mean_deg, abs=1e-3)
    assert summary["dead_reckoning"]["rot_mean_deg"] > 0.5  # the heading drift shows


def test_map_only_log_gets_map_numbers(bench_run):
    _, _, map_results, _ = bench_run
    summary = map_results["summaries"][0]
    assert not summary["scored"] and summary["seeds"] == [3]
    assert summary["map"]["wall_thickness_m"]["median"] == pytest.approx(2 * 40 / 82 * 0.1)
    assert summary["map"]["occupied_with_neighbour"]["median"] == 1.0
    assert 0.0 <= summary["map"]["half_agreement"]["median"] <= 1.0
    assert summary["dead_reckoning_map"]["half_agreement"] is not None


def test_busy_processes_run_beside_a_run_and_stop_after_it():
    with busy_processes(2) as children:
        assert len(children) == 2 and all(child.poll() is None for child in children)
        assert all(child.args[-1] == BUSY_LOOP for child in children)
    assert all(child.returncode is not None for child in children)


def test_failed_run_is_reported_not_dropped(bench_run):
    _, _, _, broken_results = bench_run
    summary = broken_results["summaries"][0]
    assert summary["seeds_ok"] == 0 and "stand-in engine failure" in summary["errors"]["3"]
    assert summary["slam"]["trans_mean_m"]["median"] is None


def test_tables_show_the_summary_numbers(bench_run):
    _, results, map_results, broken_results = bench_run
    console = Console(record=True, width=300)
    for run in (results, map_results, broken_results):
        print_report(run, console)
    text = console.export_text()
    summary = results["summaries"][0]
    trans = summary["slam"]["trans_mean_m"]
    assert f"{trans['median']:.3f} / {trans['worst']:.3f}" in text
    assert f"{summary['dead_reckoning']['rot_mean_deg']:.2f}" in text
    assert "RBPF SLAM" in text and "dead reckoning" in text and "3/3" in text
    assert "(no ground truth)" in text and "0.098 / 0.098" in text  # wall thickness of the map-only log
    assert "seed 3 failed" in text and "0/1" in text


def test_map_numbers_on_hand_made_grids():
    thick = np.zeros((20, 20))
    thick[5:8, 2:18] = 3.0  # a 3-cell-thick wall, 16 long
    grid = OccupancyGrid(thick, 0.05, 0.0, 0.0)
    assert wall_thickness_m(grid) == pytest.approx(2 * 48 / (2 * 16 + 2 * 3) * 0.05)
    speck = np.zeros((10, 10))
    speck[2, 2] = speck[2, 3] = speck[7, 7] = 3.0
    assert occupied_with_neighbour(OccupancyGrid(speck, 0.05, 0.0, 0.0)) == pytest.approx(2 / 3)
    # Two halves seeing the same wall agree; shifted by 0.3 m they do not.
    wall = np.stack([np.linspace(0, 5, 200), np.zeros(200)], axis=1)
    same = np.stack([wall, wall])
    assert half_agreement(same, 0.05)["half_agreement"] == 1.0
    shifted = np.stack([wall, wall + [0.0, 0.3]])
    moved = half_agreement(shifted, 0.05)
    assert moved["half_agreement"] == 0.0 and moved["half_mean_offset_m"] == pytest.approx(0.3, abs=0.03)


def _dense_half_agreement(endpoints: np.ndarray, resolution_m: float, window_m: float, min_hits: int) -> dict:
    """The half agreement by its definition on a dense grid: each half's hit cells, the distance
    transform of the other half's, read at them."""
    every = endpoints.reshape(-1, 2)
    every = every[np.isfinite(every[:, 0])]
    origin = every.min(axis=0) - 2 * resolution_m
    shape_xy = np.floor((every.max(axis=0) - origin) / resolution_m).astype(int) + 3
    hits = []
    for part in (endpoints[:len(endpoints) // 2], endpoints[len(endpoints) // 2:]):
        points = part.reshape(-1, 2)
        points = points[np.isfinite(points[:, 0])]
        cells = np.floor((points - origin) / resolution_m).astype(np.int64)
        counts = np.zeros((shape_xy[1], shape_xy[0]), np.int64)
        np.add.at(counts, (cells[:, 1], cells[:, 0]), 1)
        hits.append(counts >= min_hits)
    offsets = []
    for mine, theirs in ((hits[0], hits[1]), (hits[1], hits[0])):
        distance = ndimage.distance_transform_edt(~theirs)[mine] * resolution_m
        offsets.append(distance[distance <= window_m])
    every_offset = np.concatenate(offsets)
    if every_offset.size == 0:
        return {"half_agreement": float("nan"), "half_mean_offset_m": float("nan"), "half_overlap_cells": 0}
    return {"half_agreement": float(np.mean(every_offset <= resolution_m * 1.5)),
            "half_mean_offset_m": float(np.mean(every_offset)), "half_overlap_cells": int(every_offset.size)}


def test_half_agreement_equals_the_distance_transform_definition():
    rng = np.random.default_rng(3)
    overlapping = 0
    for trial in range(20):
        scans, beams = int(rng.integers(2, 30)), int(rng.integers(5, 80))
        # walls seen from both halves with a small offset, plus clutter and no-return beams
        endpoints = rng.uniform(-3, 3, (scans, beams, 2))
        endpoints[scans // 2:, : beams // 2] = endpoints[: scans - scans // 2, : beams // 2] + rng.normal(0, 0.04, 2)
        endpoints[rng.random((scans, beams)) < 0.1] = np.nan
        for min_hits in (1, 2):
            expected = _dense_half_agreement(endpoints, 0.05, 0.5, min_hits)
            got = half_agreement(endpoints, 0.05, 0.5, min_hits)
            assert got["half_overlap_cells"] == expected["half_overlap_cells"], trial
            overlapping += got["half_overlap_cells"] > 0
            assert got["half_agreement"] == pytest.approx(expected["half_agreement"], abs=1e-12, nan_ok=True)
            assert got["half_mean_offset_m"] == pytest.approx(expected["half_mean_offset_m"], abs=1e-12, nan_ok=True)
    assert overlapping >= 20  # most trials compare real overlaps, not two NaNs


def test_scoring_libraries_are_not_loaded_before_the_measured_run():
    """The worker imports the map numbers before the run whose peak memory it reports: what only the
    scoring needs (scipy.spatial, about 6 MB) loads when the scoring runs."""
    import subprocess
    import sys

    code = "import sys, bench.worker, bench.agreement; print('scipy.spatial' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_map_numbers_ignore_empty_map_around_the_walls():
    """A wall on the grid's border, and the same wall inside a much larger empty map: same numbers."""
    wall = np.zeros((6, 30))
    wall[0, :] = 3.0
    wall[3, 5:9] = 3.0
    large = np.zeros((200, 300))
    large[50:56, 100:130] = wall
    for f in (wall_thickness_m, occupied_with_neighbour):
        assert f(OccupancyGrid(wall, 0.05, 0.0, 0.0)) == f(OccupancyGrid(large, 0.05, 0.0, 0.0))
    edges = 2 * 30 + 2 + 2 * 4 + 2  # the border row's two long sides and ends, the short wall's
    assert wall_thickness_m(OccupancyGrid(wall, 0.05, 0.0, 0.0)) == pytest.approx(2 * 34 / edges * 0.05)
    assert np.isnan(wall_thickness_m(OccupancyGrid(np.zeros((4, 4)), 0.05, 0.0, 0.0)))


def test_parse_seeds():
    assert parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert parse_seeds("0,3,7-8") == [0, 3, 7, 8]


def test_relations_round_trip_through_the_test_files(tmp_path):
    folder = write_case(tmp_path / "c")
    relations: Relations = read_relations(folder / "log.relations")
    truth = ground_truth()
    assert relation_errors(truth, relations).trans_mean_m == pytest.approx(0, abs=1e-8)


def test_simulated_car_is_written_as_its_format_with_ground_truth(tmp_path):
    (case,) = simulated_cases(tmp_path)
    assert case.name == "sim-car-campus" and case.scored and case.ground_truth_path is not None
    log = load_log(case.log_path)
    assert log.source_format == "ece276a-car" and log.encoders is not None and log.gyro is not None
    truth = read_ground_truth(case.ground_truth_path)
    assert len(truth) == len(log.scans) == 703
    assert len(read_relations(case.relations_path)) > len(log.scans)  # consecutive scans and loop closures


def test_scan_end_points_use_each_scans_own_start_angle() -> None:
    import dataclasses

    from bench.agreement import scan_endpoints_world
    from slam_engine.simulation import simulate

    drive = simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=5.0, cameras=False)
    segments = drive.world.segments

    def median_wall_distance_m(log: DriveLog) -> float:
        points = scan_endpoints_world(log, drive.ground_truth, 30.0).reshape(-1, 2)
        points = points[np.isfinite(points).all(axis=1)]
        p, e = segments[:, :2], segments[:, 2:] - segments[:, :2]
        u = np.clip(((points[:, None, :] - p[None]) * e[None]).sum(-1) / (e * e).sum(-1)[None], 0.0, 1.0)
        return float(np.median(np.min(np.linalg.norm(points[:, None, :] - p[None] - u[..., None] * e[None],
                                                     axis=-1), axis=1)))

    turned = median_wall_distance_m(drive.log)
    unturned = median_wall_distance_m(dataclasses.replace(
        drive.log, scans=dataclasses.replace(drive.log.scans, angle_offset_rad=None)))
    print(f"median end point to wall: {turned:.4f} m with each scan's start angle, {unturned:.4f} m without")
    assert turned < 0.008 < unturned
