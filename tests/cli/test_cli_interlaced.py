"""An interlaced laser (each scan starts 0.25 deg later than the one before, four start angles, cycling)
through ``lidarmap run``: mapped as well as the same simulated drive without interlacing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lidarmap.cli import app
from slam_engine.evaluation.metrics import absolute_trajectory_error, read_ground_truth
from slam_engine.formats import load_log
from slam_engine.products import read_trajectory
from slam_engine.simulation import simulate, write_simulated

pytestmark = pytest.mark.slow

# Measured (seed 0, 40 s, 10 particles): 0.0066 m with interlacing, 0.0062 m without; with 60 s drives
# and seeds 0 / 1 the interlaced drive was 0.0003 / 0.0029 m worse. The margin is three times that spread.
MARGIN_M = 0.009


def _mapped_ate(tmp_path: Path, rig: str) -> tuple[float, dict]:
    log = write_simulated(simulate("office", seed=0, rig=rig, max_duration_s=40.0, cameras=False), "carmen",
                          tmp_path / rig)
    out = tmp_path / f"{rig}-out"
    result = CliRunner().invoke(app, ["run", str(log), "--out", str(out), "--particles", "10", "--seed", "0"])
    assert result.exit_code == 0, result.output
    ate = absolute_trajectory_error(read_trajectory(out / "trajectory.json"),
                                    read_ground_truth(tmp_path / rig / "ground_truth.txt"))
    return ate, json.loads((out / "run.json").read_text())


def test_interlaced_laser_maps_as_well_as_the_same_drive_without_interlacing(tmp_path: Path) -> None:
    written = load_log(write_simulated(simulate("office", seed=0, rig="carmen-interlaced", max_duration_s=5.0,
                                                cameras=False), "carmen", tmp_path / "short"))
    assert np.degrees(np.unique(np.round(written.scans.angle_offset_rad, 9))) == pytest.approx([0, 0.25, 0.5, 0.75])
    interlaced, run = _mapped_ate(tmp_path, "carmen-interlaced")
    plain, _ = _mapped_ate(tmp_path, "carmen-robot")
    print(f"ATE interlaced {interlaced:.4f} m, not interlaced {plain:.4f} m")
    assert any("beam geometry changes from scan to scan" in w for w in run["warnings"])
    assert plain < 0.03
    assert interlaced <= plain + MARGIN_M
