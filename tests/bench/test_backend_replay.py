"""bench.backend_replay: a recorded front end replayed through the back end gives what the full run's
back end gave (same closures), so back-end experiments on recordings stand for full runs."""

from __future__ import annotations

import json

import numpy as np

from bench.backend_replay import main, record, replay
from slam_engine.config import SlamConfig
from slam_engine.formats import load_log
from slam_engine.model.result import Trajectory
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate, write_simulated


def test_replay_reproduces_the_full_runs_back_end(tmp_path, capsys) -> None:
    log_path = write_simulated(simulate("office", seed=0, cameras=False), "carmen", tmp_path / "office")
    overrides = {"particles": 5}
    recording = record(str(log_path), 0, tmp_path / "fe", overrides)
    full = run_slam(load_log(log_path), SlamConfig.model_validate({**overrides, "seed": 0}))
    expected = full.input_summary["loop_closing"]
    row = replay(recording, {})
    assert expected["closures_accepted"] >= 1  # the office loop closes: the comparison means something
    for key in ("submaps", "candidates_matched", "closures_accepted", "largest_correction_m"):
        assert row[key] == expected[key], key
    data = np.load(recording)
    assert len(data["t_s"]) == len(data["path"]) and not np.isnan(data["t_s"]).any()
    assert np.all(np.diff(data["t_s"]) > 0)
    # settings reach the back end: without it no closure is matched
    assert replay(recording, {"loop_closing": {"enabled": False}})["candidates_matched"] == 0
    # the command line: one JSON row per recording
    assert main(["replay", str(tmp_path / "fe"), "--set", "loop_closing.min_score=0.99"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(rows) == 1 and rows[0]["closures_accepted"] <= expected["closures_accepted"]


def test_false_closures_are_those_off_the_ground_truth() -> None:
    from bench.backend_replay import false_closures
    from slam_engine.backend.loop_closer import Closure

    # truth: a straight drive along x, one scan per second, 1 m apart
    truth = Trajectory(t_s=np.arange(20.0), poses=np.column_stack([np.arange(20.0), np.zeros(20), np.zeros(20)]))
    key_frame_t_s = np.arange(20.0)

    def closure(node: int, anchor: int, x_m: float, accepted: bool = True) -> Closure:
        return Closure(node, 0, anchor, 0.8, 0.0, 1.0, 0.1, accepted, "accepted", 0.0, 0.0, (x_m, 0.0, 0.0))

    right = closure(15, 2, 13.05)  # 13 m apart in truth
    aliased = closure(16, 2, 14.0 + 14.0)  # the next bay, 14 m on
    ignored = closure(17, 2, 0.0, accepted=False)  # rejected closures are not counted
    found = false_closures([right, aliased, ignored], key_frame_t_s, truth)
    assert [(f["node"], f["off_m"]) for f in found] == [(16, 14.0)]


def test_a_recording_of_a_drive_on_open_ground_has_the_full_runs_front_end(tmp_path) -> None:
    """The campus driven by the robot's level LiDAR is open ground (a fifth of its beams return nothing):
    ``lidarmap run`` maps it without no-return clearing, and so does the recorded front end."""
    log_path = write_simulated(simulate("campus", seed=0, cameras=False, max_duration_s=20.0), "carmen",
                               tmp_path / "campus")
    recording = record(str(log_path), 0, tmp_path / "fe", {"particles": 3})
    recorded = SlamConfig.model_validate_json(str(np.load(recording)["config"]))
    assert recorded.grid.no_return_clear_m == 0.0
    full = run_slam(load_log(log_path), SlamConfig.model_validate({"particles": 3, "seed": 0}))
    assert full.input_summary["open_ground"]["open_ground"] and full.config.grid == recorded.grid
    expected, row = full.input_summary["loop_closing"], replay(recording, {})
    for key in ("submaps", "candidates_matched", "closures_accepted"):
        assert row[key] == expected[key], key
