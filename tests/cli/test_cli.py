"""The ``lidarmap run`` and ``lidarmap evaluate`` commands: products, accuracy figures, one-line errors."""

from __future__ import annotations

import json
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import rasterio
from log_helpers import saturated_log
from PIL import Image
from typer.testing import CliRunner

from lidarmap.cli import app
from slam_engine import pipeline
from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import read_ground_truth, read_relations
from slam_engine.model.result import OccupancyGrid, ScanStats, SlamResult, Trajectory
from slam_engine.products import write_trajectory_json, write_trajectory_tum

runner = CliRunner()
INTEL = "benchmark/intel.clf"


def invoke(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def assert_one_line_bad_input(result, *fragments: str) -> None:
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0]


# --- bad input: one line, exit code 2 ---------------------------------------------------------

def test_missing_log_is_one_line_and_exit_2(tmp_path: Path) -> None:
    assert_one_line_bad_input(invoke("run", tmp_path / "nope.clf", "--out", tmp_path / "out"),
                              "nope.clf", "no such file")
    assert not (tmp_path / "out").exists()


def test_bad_config_file_names_the_file_and_the_field(tmp_path: Path, dataset) -> None:
    config = tmp_path / "slam.yaml"
    config.write_text("particles: -3\ngrid:\n  resolution_m: 0.05\n")
    assert_one_line_bad_input(invoke("run", dataset(INTEL), "--out", tmp_path / "o", "--config", config),
                              "slam.yaml", "particles", "greater than or equal to 1")
    config.write_text("- 1\n- 2\n")
    assert_one_line_bad_input(invoke("run", dataset(INTEL), "--out", tmp_path / "o", "--config", config),
                              "mapping")
    config.write_text("grid: {resolution_m: 0.05\n")
    assert_one_line_bad_input(invoke("run", dataset(INTEL), "--out", tmp_path / "o", "--config", config),
                              "slam.yaml")


def test_bad_options_are_one_line(tmp_path: Path, dataset) -> None:
    log = dataset(INTEL)
    assert_one_line_bad_input(invoke("run", log, "--out", tmp_path, "--resolution", "5"), "grid.resolution_m")
    assert_one_line_bad_input(invoke("run", log, "--out", tmp_path, "--lat", "48.1"), "--heading")
    assert_one_line_bad_input(invoke("run", log, "--out", tmp_path, "--lat", "89", "--lon", "1", "--heading", "0"),
                              "latitude 89")
    assert_one_line_bad_input(invoke("run", log, "--out", tmp_path, "--format", "laserfile"), "unknown format")


def test_bad_relations_file_fails_before_the_run_with_file_and_line(tmp_path: Path, dataset) -> None:
    relations = tmp_path / "bad.relations"
    relations.write_text("1 2 0 0 0 0 0 0\n3 4 0 0\n")
    assert_one_line_bad_input(invoke("run", dataset(INTEL), "--out", tmp_path / "o", "--relations", relations),
                              "bad.relations", "line 2")


def test_verbose_shows_the_traceback_and_still_exits_2(tmp_path: Path) -> None:
    result = invoke("run", tmp_path / "nope.clf", "--out", tmp_path / "o", "--verbose")
    assert result.exit_code == 2
    assert "Traceback" in result.stderr and result.stderr.strip().splitlines()[-1].startswith("error: ")


# --- evaluate -------------------------------------------------------------------------------------

def test_evaluate_scaled_trajectory_gives_the_expected_relation_error(tmp_path: Path, dataset) -> None:
    truth_path = dataset("benchmark/intel.gt.txt")
    relations_path = dataset("benchmark/intel.relations")
    truth = read_ground_truth(truth_path)
    scaled = Trajectory(truth.t_s, np.column_stack([1.01 * truth.poses[:, :2], truth.poses[:, 2]]))
    write_trajectory_tum(scaled, tmp_path / "scaled.tum")
    result = invoke("evaluate", tmp_path / "scaled.tum", "--relations", relations_path,
                    "--ground-truth", truth_path, "--json")
    assert result.exit_code == 0, result.output
    figures = json.loads(result.stdout)
    relations = read_relations(relations_path)
    expected = 0.01 * np.hypot(relations.motion[:, 0], relations.motion[:, 1])  # scaling every relation by 1.01
    assert figures["relations"]["all"]["n_relations"] == len(relations) == 1818
    assert figures["relations"]["all"]["trans_mean_m"] == pytest.approx(expected.mean(), rel=1e-5)
    assert figures["relations"]["all"]["rot_mean_deg"] == pytest.approx(0.0, abs=1e-5)
    assert figures["ate_m"] > 0.01


def test_evaluate_rigidly_moved_json_trajectory_has_zero_error_and_prints_a_table(tmp_path: Path, dataset) -> None:
    truth_path = dataset("benchmark/intel.gt.txt")
    truth = read_ground_truth(truth_path)
    c, s = np.cos(0.7), np.sin(0.7)
    xy = truth.poses[:, :2] @ np.array([[c, s], [-s, c]]) + [5.0, -2.0]
    write_trajectory_json(Trajectory(truth.t_s, np.column_stack([xy, truth.poses[:, 2] + 0.7])), tmp_path / "t.json")
    result = invoke("evaluate", tmp_path / "t.json", "--relations", dataset("benchmark/intel.relations"),
                    "--ground-truth", truth_path)
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("relations all  : trans 0.0000 +- 0.0000 m, rot 0.000 +- 0.000 deg (1818 scored")
    assert lines[-1] == "ATE (rigid 2-D alignment): 0.0000 m"


def test_evaluate_bad_input_is_one_line(tmp_path: Path, dataset) -> None:
    relations = dataset("benchmark/intel.relations")
    assert_one_line_bad_input(invoke("evaluate", tmp_path / "none.tum", "--relations", relations), "none.tum")
    (tmp_path / "t.tum").write_text("1 2 3\n")
    assert_one_line_bad_input(invoke("evaluate", tmp_path / "t.tum", "--relations", relations),
                              "t.tum", "line 1", "TUM")
    assert_one_line_bad_input(invoke("evaluate", dataset("benchmark/intel.gt.txt")), "--relations")
    # a binary file as the trajectory or the relations: one line naming it, exit 2 (was a traceback, exit 1)
    (tmp_path / "binary.dat").write_bytes(bytes(range(256)) * 8)
    assert_one_line_bad_input(invoke("evaluate", tmp_path / "binary.dat", "--relations", relations),
                              "binary.dat", "not a text trajectory")
    assert_one_line_bad_input(invoke("evaluate", dataset("benchmark/intel.gt.txt"), "--relations",
                                     tmp_path / "binary.dat"), "binary.dat", "not a text relation")


# --- run ------------------------------------------------------------------------------------------

ALL_PRODUCTS = {"trajectory.json", "trajectory.tum", "dead_reckoning.json", "dead_reckoning.tum", "occupancy.png",
                "occupancy_trajectory.png", "occupancy.tif", "map.pgm", "map.yaml", "animation.gif", "run.json"}


def test_run_wires_log_config_progress_relations_and_products(tmp_path: Path, dataset,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """With a stand-in engine that returns the ground truth as its trajectory: the automatically found
    relations and ground truth score it at zero error; the config carries the CLI overrides."""
    log = dataset(INTEL)
    truth = read_ground_truth(dataset("benchmark/intel.gt.txt"))
    calls = {}

    def run_slam(drive_log, config, rng=None, progress=None, live_previews=None):
        calls.update(config=config, scans=len(drive_log.scans), rng=rng, live_previews=live_previews)
        for done in range(0, len(drive_log.scans) + 1, 100):
            progress(pipeline.RunProgress(scans_done=done, scans_total=len(drive_log.scans), elapsed_s=0.1))
        log_odds = np.zeros((80, 120))
        log_odds[10:70, 60] = 5.0
        grid = OccupancyGrid(log_odds, config.grid.resolution_m, -3.0, -2.0)
        stats = ScanStats(*(np.zeros(3) for _ in range(6)))
        return SlamResult(trajectory=truth, dead_reckoning=truth, grid=grid, scan_stats=stats, config=config,
                          snapshots=[], wall_time_s=1.5)

    monkeypatch.setitem(sys.modules, "slam_engine.pipeline",
                        types.SimpleNamespace(**{**vars(pipeline), "run_slam": run_slam}))
    out = tmp_path / "out"
    result = invoke("run", log, "--out", out, "--particles", "12", "--seed", "5", "--resolution", "0.1")
    assert result.exit_code == 0, result.output
    config: SlamConfig = calls["config"]
    assert (config.particles, config.seed, config.grid.resolution_m) == (12, 5, 0.1)
    assert config.snapshot_every_scans == 0 and calls["scans"] == 910  # no animation unless asked for
    assert calls["rng"] is None  # the seed reaches the engine through the config only (config.seed above)
    assert calls["live_previews"] is False  # the progress bar shows counts, no preview maps
    run = json.loads((out / "run.json").read_text())
    assert run["accuracy"]["relations"]["all"]["n_relations"] == 1818
    assert run["accuracy"]["relations"]["all"]["trans_mean_m"] < 1e-5 and run["accuracy"]["ate_m"] < 1e-9
    assert run["input"]["format"] == "carmen" and run["input"]["streams"]["scans"] == 910
    assert ALL_PRODUCTS - {"animation.gif"} == {p.name for p in out.iterdir()}
    assert "relation error: 0.000 +- 0.000 m" in result.stdout
    assert "animation.gif not drawn" not in result.stdout  # the stand-in result has no bundle to draw it from
    # --animation: about 40 frames over the drive; --snapshot-every sets them, 0 still none
    assert invoke("run", log, "--out", tmp_path / "anim", "--animation").exit_code == 0
    assert calls["config"].snapshot_every_scans == 910 // 40
    assert invoke("run", log, "--out", tmp_path / "every", "--animation", "--snapshot-every", "7").exit_code == 0
    assert calls["config"].snapshot_every_scans == 7
    assert invoke("run", log, "--out", tmp_path / "none", "--animation", "--snapshot-every", "0").exit_code == 0
    assert calls["config"].snapshot_every_scans == 0


def test_run_progress_bar_names_each_stage_in_order_and_ends_after_the_products(tmp_path: Path) -> None:
    """A real run on a short simulated drive, its bar drawn as on a terminal: the stages in order, the
    share done never backwards, 100 % only once the products are being written."""
    from slam_engine.simulation import simulate, write_simulated

    log = write_simulated(simulate("office", seed=3, rig="carmen-robot", max_duration_s=15.0), "carmen", tmp_path)
    result = CliRunner().invoke(app, ["run", str(log), "--out", str(tmp_path / "out"), "--particles", "3"],
                                env={"TTY_COMPATIBLE": "1", "COLUMNS": "160"})
    assert result.exit_code == 0, result.output
    drawn = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", result.stderr).replace("\r", "\n")  # one line a redraw
    lines = re.findall(r"^(mapping scans|closing loops|aligning to the map|rendering the map|writing products|done)"
                       r" +\S*\s+(\d+)%", drawn, re.MULTILINE)
    stages, percents = [stage for stage, _ in lines], [int(percent) for _, percent in lines]
    shown = [s for i, s in enumerate(stages) if i == 0 or s != stages[i - 1]]
    assert shown == ["mapping scans", "closing loops", "aligning to the map", "rendering the map",
                     "writing products", "done"]
    assert percents == sorted(percents) and percents[-1] == 100
    assert percents[stages.index("writing products")] == 97 and percents.count(100) == stages.count("done")


def test_run_progress_without_a_terminal_is_a_plain_line_per_stage(tmp_path: Path) -> None:
    """stderr a log file or a pipe: no bar (it printed only "done 100%" at the end), a line when each stage
    starts and at every tenth of the scans mapped, in order, the share done never backwards."""
    from slam_engine.simulation import simulate, write_simulated

    log = write_simulated(simulate("office", seed=3, rig="carmen-robot", max_duration_s=15.0), "carmen", tmp_path)
    result = CliRunner().invoke(app, ["run", str(log), "--out", str(tmp_path / "out"), "--particles", "3"])
    assert result.exit_code == 0, result.output
    assert "\x1b" not in result.stderr and "\r" not in result.stderr  # nothing drawn over
    lines = re.findall(r"^ *[\d.]+ s  (mapping scans|closing loops|aligning to the map|rendering the map|"
                       r"writing products|done) +(\d+)%", result.stderr, re.MULTILINE)
    stages, percents = [stage for stage, _ in lines], [int(percent) for _, percent in lines]
    shown = [s for i, s in enumerate(stages) if i == 0 or s != stages[i - 1]]
    assert shown == ["mapping scans", "closing loops", "aligning to the map", "rendering the map",
                     "writing products", "done"]
    assert percents == sorted(percents) and percents[-1] == 100
    assert 5 <= stages.count("mapping scans") <= 11  # its start and the tenths of the scans


def test_run_prints_each_run_json_warning_as_one_line_on_stderr(tmp_path: Path) -> None:
    log = saturated_log(tmp_path / "sim")
    result = CliRunner().invoke(app, ["run", str(log), "--out", str(tmp_path / "out"), "--particles", "3"])
    assert result.exit_code == 0, result.output
    recorded = json.loads((tmp_path / "out" / "run.json").read_text())["warnings"]
    assert f"{log}: FLASER: range 30 m fills many beams; treated as no return" in recorded
    printed = [line for line in result.stderr.splitlines() if line.startswith("warning: ")]
    assert printed == [f"warning: {warning}" for warning in recorded]
    assert "warning" not in result.stdout


@pytest.mark.slow
def test_run_on_intel_writes_every_product(tmp_path: Path, dataset) -> None:
    out = tmp_path / "intel"
    result = invoke("run", dataset(INTEL), "--out", out, "--particles", "5", "--seed", "1", "--resolution", "0.1",
                    "--animation")
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} >= ALL_PRODUCTS
    run = json.loads((out / "run.json").read_text())
    assert run["timings"]["scans"] == 910 and run["config"]["particles"] == 5
    relations = run["accuracy"]["relations"]["all"]
    assert relations["n_relations"] == 1818 and relations["n_failed"] == 0
    assert np.isfinite(relations["trans_mean_m"]) and np.isfinite(run["accuracy"]["ate_m"])
    # the map agrees with its own scans: a few key frames at most are contradicted, and nothing is flagged
    consistency = run["map"]["consistency"]
    assert consistency["flagged"] is False and consistency["key_frames_judged"] > 800
    assert consistency["key_frames_contradicted_share"] < 0.05
    with rasterio.open(out / "occupancy.tif") as ds:
        assert (ds.width, ds.height) == Image.open(out / "occupancy.png").size
    assert Image.open(out / "animation.gif").n_frames >= 2
