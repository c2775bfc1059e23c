"""bench.backend_replay: a recorded front end replayed through the back end gives what the full run's
back end gave (same closures), so back-end experiments on recordings stand for full runs."""

from __future__ import annotations

import json

import numpy as np

from bench.backend_replay import main, record, replay
from slam_engine.config import SlamConfig
from slam_engine.formats import load_log
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
