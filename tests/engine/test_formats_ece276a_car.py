"""ECE276A car logs: the real calibration files, simulated sensor_data in the documented layout,
missing calibration and bad rows."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from slam_engine.errors import LogFormatError
from slam_engine.formats import ece276a_car, load_log
from slam_engine.model.drive_log import MotionModelKind
from slam_engine.simulation import simulate, write_simulated


def test_real_calibration_gives_the_provenance_transforms(dataset) -> None:
    param = dataset("ece276a-car/param")
    vehicle = ece276a_car.read_vehicle(param)
    assert vehicle.kind == MotionModelKind.DIFFERENTIAL
    assert vehicle.ticks_per_revolution == 4096
    assert vehicle.wheel_diameters_m == pytest.approx((0.623479, 0.622806))
    assert vehicle.track_width_m == pytest.approx(1.52439)
    assert vehicle.T_vehicle_from_gyro[:3, 3] == pytest.approx([-0.335, -0.035, 0.78])
    lidar = ece276a_car.read_lidar(param, 286)
    T = lidar.T_vehicle_from_lidar
    assert T[:3, 3] == pytest.approx([0.8349, -0.0126869, 1.76416])
    assert T[0] == pytest.approx([0.00130201, 0.796097, 0.605167, 0.8349])
    assert T[2, :3] == pytest.approx([-0.00102038, 0.605169, -0.796097])
    # The stated RPY (XYZ extrinsic, deg) is the rotation matrix's: R = Rz(yaw) Ry(pitch) Rx(roll).
    assert ece276a_car.rpy_deg(T[:3, :3]) == pytest.approx((142.759, 0.0584636, 89.9254), abs=1e-3)
    stereo = ece276a_car.read_extrinsic(param, "Vehicle2Stereo.txt")
    assert ece276a_car.rpy_deg(stereo[:3, :3]) == pytest.approx((-90.878, 0.0132, -90.3899), abs=1e-3)
    assert stereo[:3, 3] == pytest.approx([1.64239, 0.247401, 1.58411])
    assert np.degrees(lidar.beam_angles_rad[[0, -1]]) == pytest.approx([-5.0, 185.0])
    assert np.degrees(lidar.angle_increment_rad) == pytest.approx(0.6667, abs=1e-4)
    assert lidar.range_max_m == 80.0


def test_lidar_beam_count_must_fit_the_stated_resolution(dataset) -> None:
    with pytest.raises(LogFormatError, match="stated resolution is 0.666 deg"):
        ece276a_car.read_lidar(dataset("ece276a-car/param"), 200)


@pytest.fixture(scope="module")
def car_drive():
    return simulate(seed=1, rig="car", scenario="campus", max_duration_s=8.0, cameras=False)


def test_simulated_log_with_the_real_param_folder(dataset, car_drive, tmp_path) -> None:
    write_simulated(car_drive, "ece276a-car", tmp_path)
    shutil.rmtree(tmp_path / "param")
    shutil.copytree(dataset("ece276a-car/param"), tmp_path / "param")
    log = load_log(tmp_path)
    assert log.lidar.num_beams == 286 and len(log.scans) == len(car_drive.log.scans)
    np.testing.assert_allclose(log.lidar.T_vehicle_from_lidar, car_drive.log.lidar.T_vehicle_from_lidar, atol=1e-9)
    ranges = (tmp_path / "sensor_data" / "lidar.csv").read_text().splitlines()[0].split(",")
    assert len(ranges) == 287 and int(ranges[0]) > 1.5e18  # nanosecond stamps
    assert log.gyro.yaw_rate_rad_s == pytest.approx(car_drive.log.gyro.yaw_rate_rad_s, abs=1e-5)


def test_stereo_folder_is_paired_by_stamp_or_reported(dataset, car_drive, tmp_path) -> None:
    write_simulated(car_drive, "ece276a-car", tmp_path)
    shutil.rmtree(tmp_path / "param")
    shutil.copytree(dataset("ece276a-car/param"), tmp_path / "param")
    for side in ("stereo_left", "stereo_right"):
        (tmp_path / "stereo_images" / side).mkdir(parents=True)
        shutil.copy(dataset(f"ece276a-car/stereo_sample/image_{side[7:]}.png"),
                    tmp_path / "stereo_images" / side / "1544582648100000000.png")
    log = load_log(tmp_path)
    if log.stereo is None:  # the texture package's calibration reader is not in this build
        assert any("stereo calibration reader not available" in w for w in log.warnings)
    else:
        assert len(log.stereo) == 1 and log.stereo.t_s[0] == pytest.approx(1544582648.1)
        assert log.stereo.calibration.baseline_m == pytest.approx(0.4751, abs=1e-3)


def test_missing_calibration_and_bad_rows(car_drive, tmp_path) -> None:
    write_simulated(car_drive, "ece276a-car", tmp_path)
    (tmp_path / "param" / "Vehicle2Lidar.txt").unlink()
    with pytest.raises(LogFormatError, match=r"Vehicle2Lidar.txt: missing calibration file"):
        load_log(tmp_path)
    write_simulated(car_drive, "ece276a-car", tmp_path)
    lidar_csv = tmp_path / "sensor_data" / "lidar.csv"
    lines = lidar_csv.read_text().splitlines()
    lidar_csv.write_text("\n".join(lines[:5] + [lines[5][:200]]) + "\n")
    with pytest.raises(LogFormatError, match=r"lidar.csv, line 6: row has \d+ fields, expected 287"):
        load_log(tmp_path)
    fields = lines[3].split(",")
    fields[10] = "-1.5"
    lidar_csv.write_text("\n".join(lines[:3] + [",".join(fields)] + lines[4:]) + "\n")
    with pytest.raises(LogFormatError, match=r"line 4: negative range -1.5 at beam 9"):
        load_log(tmp_path)
    encoder_csv = tmp_path / "sensor_data" / "encoder.csv"
    rows = encoder_csv.read_text().splitlines()
    encoder_csv.write_text("\n".join(rows[::-1]) + "\n")
    with pytest.raises(LogFormatError, match="encoder timestamps are not in time order"):
        load_log(tmp_path / ".", format="ece276a-car")
    (tmp_path / "sensor_data" / "lidar.csv").unlink()
    encoder_csv.write_text("\n".join(rows) + "\n")
    log = load_log(tmp_path)
    assert log.scans is None and any("dead reckoning only" in w for w in log.warnings)
