"""Cameras in the simulator: the car's stereo pair and THOR's Kinect, rendered from the world's floor
texture, written in their log formats, read back, and mapped into a texture that reproduces the
floor (colour error bounded, placed within one cell). Drives are 3 s long (3 camera frames)."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from slam_engine.config import SlamConfig
from slam_engine.errors import LogFormatError
from slam_engine.formats import load_log
from slam_engine.pipeline import run_slam
from slam_engine.simulation import GROUND_TEXTURE_FILE, RIGS, floor_beside_log, simulate, write_simulated
from slam_engine.texture.accuracy import map_to_truth_frame, texture_accuracy
from slam_engine.texture.images import read_frame


@functools.cache
def drive(rig: str):
    return simulate(scenario=None, seed=0, rig=rig, max_duration_s=3.0)


def test_thor_kinect_frames_map_the_office_floor(tmp_path) -> None:
    thor = drive("thor")
    assert len(thor.log.rgbd) == 3 and thor.log.stereo is None
    write_simulated(thor, "thor", tmp_path)
    loaded = load_log(tmp_path)
    assert len(loaded.rgbd) == 3
    assert np.array_equal(read_frame(loaded.rgbd.depth_images[0], "d"), thor.log.rgbd.depth_images[0])
    assert np.array_equal(read_frame(loaded.rgbd.rgb_images[2], "rgb"), thor.log.rgbd.rgb_images[2])
    result = run_slam(loaded, SlamConfig())
    assert result.texture is not None
    rotation, translation = map_to_truth_frame(result.trajectory, thor.ground_truth)
    accuracy = texture_accuracy(result.texture, floor_beside_log(tmp_path), rotation, translation)
    assert accuracy.observed_cells > 3000  # measured 7581 cells of 5 cm
    assert accuracy.colour_error_mean < 20.0  # measured 11-17 of 255 (2 cm speckle, 1.5 cm grout in 5 cm cells)
    assert max(map(abs, accuracy.placement_offset_cells)) <= 1  # placed within one cell


def test_lidarmap_run_on_the_simulated_car_gives_a_texture_and_its_accuracy(tmp_path) -> None:
    from lidarmap.cli import app

    runner = CliRunner()
    log, out = tmp_path / "car", tmp_path / "out"
    result = runner.invoke(app, ["simulate", "--format", "ece276a-car", "--out", str(log), "--duration", "3"])
    assert result.exit_code == 0, result.output
    # the course's layout: frames named by their ns stamps, the pair's calibration in param/
    for name in ("left_camera.yaml", "right_camera.yaml", "stereo_param.txt", "Vehicle2Stereo.txt"):
        assert (log / "param" / name).is_file()
    assert len(list((log / "stereo_images" / "stereo_left").glob("*.png"))) == 3
    loaded = load_log(log)
    written, read = RIGS["car"].stereo, loaded.stereo.calibration
    for field in ("K_left", "D_left", "R_left", "P_left", "K_right", "D_right", "R_right", "P_right",
                  "T_vehicle_from_camera"):
        np.testing.assert_allclose(getattr(read, field), getattr(written, field), atol=1e-6, err_msg=field)
    assert read.baseline_m == pytest.approx(0.4751436) and read.image_size_wh == (1280, 560)
    assert read.bayer_pattern == "BG" and read_frame(loaded.stereo.left_images[1], "left").shape == (560, 1280)
    assert json.loads((log / GROUND_TEXTURE_FILE).read_text())["scenario"] == "campus"

    result = runner.invoke(app, ["run", str(log), "--out", str(out), "--particles", "5", "--snapshot-every", "0"])
    assert result.exit_code == 0, result.output
    assert (out / "texture.png").is_file() and (out / "texture.tif").is_file()
    texture = json.loads((out / "run.json").read_text())["accuracy"]["texture"]
    assert texture["observed_cells"] > 20000  # measured 36,000 cells (3 stereo pairs, 4-10 m ahead)
    assert texture["colour_error_mean"] < 20.0  # measured 11-12 of 255
    assert max(map(abs, texture["placement_offset_cells"])) <= 1  # placed within one cell
    assert "texture: colour error" in result.output


def test_a_damaged_ground_texture_file_is_a_clear_error(tmp_path) -> None:
    (tmp_path / GROUND_TEXTURE_FILE).write_text('{"scenario": "moon"}')
    with pytest.raises(LogFormatError, match="unknown scenario 'moon'"):
        floor_beside_log(tmp_path)
    (tmp_path / GROUND_TEXTURE_FILE).write_text("not json")
    with pytest.raises(LogFormatError, match="not a ground-texture file"):
        floor_beside_log(tmp_path / "some_log_file")
    assert floor_beside_log(tmp_path / "elsewhere" / "log") is None
