"""Camera calibrations: the ECE276A car's param folder and the THOR Kinect constants, checked
against the numbers in the datasets' PROVENANCE.md."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from slam_engine.errors import LogFormatError
from slam_engine.texture.calibration import load_ece276a_stereo_calibration, thor_kinect_calibration


@pytest.fixture
def car_params(dataset):
    return dataset("ece276a-car/param")


def test_car_stereo_calibration_matches_provenance(car_params):
    cal = load_ece276a_stereo_calibration(car_params)
    assert cal.image_size_wh == (1280, 560)
    assert cal.K_left[0, 0] == pytest.approx(816.9037899)
    assert cal.K_left[1, 1] == pytest.approx(811.5680383)
    assert cal.K_left[0, 2] == pytest.approx(608.5072628)
    assert cal.K_left[1, 2] == pytest.approx(263.4759976)
    assert cal.D_left.shape == (5,)
    assert cal.D_left[0] == pytest.approx(-5.61430278e-02)
    for P in (cal.P_left, cal.P_right):
        assert P[0, 0] == pytest.approx(775.3723555)
        assert P[0, 2] == pytest.approx(619.4730911)
        assert P[1, 2] == pytest.approx(257.1804905)
    assert cal.P_right[0, 3] == pytest.approx(-368.4175874)
    assert cal.baseline_m == pytest.approx(0.475143600050775)
    # The rectified projection's Tx = -f * B agrees with the stated baseline to 0.1 mm.
    assert -cal.P_right[0, 3] / cal.P_right[0, 0] == pytest.approx(cal.baseline_m, abs=1e-4)
    np.testing.assert_allclose(cal.T_vehicle_from_camera[:3, 3], [1.64239, 0.247401, 1.58411])
    np.testing.assert_allclose(cal.T_vehicle_from_camera[0, :3], [-0.00680499, -0.0153215, 0.99985])
    # Optical frame: z (viewing direction) forward, x right, y down in the vehicle frame.
    R = cal.T_vehicle_from_camera[:3, :3]
    assert R[:, 2] @ [1, 0, 0] > 0.999
    assert R[:, 0] @ [0, -1, 0] > 0.999
    assert R[:, 1] @ [0, 0, -1] > 0.999
    assert cal.bayer_pattern == "BG"


def test_thor_kinect_calibration_matches_provenance():
    cal = thor_kinect_calibration()
    assert cal.fx == cal.fy == pytest.approx(585.05108211)
    assert (cal.cx, cal.cy) == pytest.approx((315.83800193, 242.94140713))
    assert cal.image_size_wh == (640, 480)
    T = cal.T_vehicle_from_camera
    np.testing.assert_allclose(T[:3, 3], [0.18, 0.005, 0.36])
    pitch, yaw = 0.36, 0.021
    # The optical axis looks forward and 0.36 rad down, turned 0.021 rad to the left.
    np.testing.assert_allclose(T[:3, 2], [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)],
                               atol=1e-12)
    # Image x (right) is horizontal (roll 0) and points to the vehicle's right.
    np.testing.assert_allclose(T[:3, 0], [np.sin(yaw), -np.cos(yaw), 0.0], atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_missing_calibration_file_names_it(car_params, tmp_path):
    for name in ("left_camera.yaml", "right_camera.yaml", "stereo_param.txt"):
        shutil.copy(car_params / name, tmp_path / name)
    with pytest.raises(LogFormatError, match="Vehicle2Stereo.txt") as info:
        load_ece276a_stereo_calibration(tmp_path)
    assert info.value.path.endswith("Vehicle2Stereo.txt")


def test_malformed_extrinsic_names_the_field(car_params, tmp_path):
    for name in ("left_camera.yaml", "right_camera.yaml", "stereo_param.txt"):
        shutil.copy(car_params / name, tmp_path / name)
    (tmp_path / "Vehicle2Stereo.txt").write_text("RPY: 0 0 0\nR: 1 0 0 0 1 0 0 0\nT: 1 2 3\n")
    with pytest.raises(LogFormatError, match="8 numbers, expected 9") as info:
        load_ece276a_stereo_calibration(tmp_path)
    assert info.value.location == "R"


def test_malformed_camera_yaml_names_the_field(car_params, tmp_path):
    for name in ("right_camera.yaml", "stereo_param.txt", "Vehicle2Stereo.txt"):
        shutil.copy(car_params / name, tmp_path / name)
    text = (car_params / "left_camera.yaml").read_text().replace("projection_matrix", "projection_matrx")
    (tmp_path / "left_camera.yaml").write_text(text)
    with pytest.raises(LogFormatError) as info:
        load_ece276a_stereo_calibration(tmp_path)
    assert info.value.location == "projection_matrix"
    assert info.value.path.endswith("left_camera.yaml")
