"""Every format round-trips a simulated drive: simulate -> write -> load -> the same streams within
the format's precision; ``load_log(folder)`` finds the log that ``write_simulated`` put there."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.formats import detect_format, load_log, write_log
from slam_engine.formats import thor as thor_format
from slam_engine.simulation import rig_for_format, simulate, write_simulated

# format -> (range tolerance [m], stamp tolerance [s])
PRECISION = {
    "carmen": (5e-4, 1e-6),
    "breezyslam": (5e-4, 1e-6),
    "thor": (0.0, 0.0),
    "ece276a-car": (5e-4, 1e-6),
    "rosbag": (0.0, 1e-9),
    "drivelog": (0.0, 0.0),
}


@pytest.fixture(scope="module")
def drives():
    cache = {}

    def get(format: str):
        if format not in cache:
            cache[format] = simulate(seed=3, rig=rig_for_format(format), scenario=None, max_duration_s=12.0,
                                     cameras=False)
        return cache[format]

    return get


def assert_scans_equal(loaded, original, range_tol: float, stamp_tol: float, planar: bool = False) -> None:
    np.testing.assert_allclose(loaded.scans.t_s, original.scans.t_s, rtol=0, atol=max(stamp_tol, 1e-12))
    np.testing.assert_array_equal(np.isinf(loaded.scans.ranges_m), np.isinf(original.scans.ranges_m))
    finite = np.isfinite(original.scans.ranges_m)
    np.testing.assert_allclose(loaded.scans.ranges_m[finite], original.scans.ranges_m[finite], rtol=0,
                               atol=range_tol + 1e-6)
    assert loaded.lidar.num_beams == original.lidar.num_beams
    assert loaded.lidar.angle_min_rad == pytest.approx(original.lidar.angle_min_rad, abs=1e-6)
    assert loaded.lidar.angle_increment_rad == pytest.approx(original.lidar.angle_increment_rad, rel=1e-6)
    T_loaded, T_original = loaded.lidar.T_vehicle_from_lidar, original.lidar.T_vehicle_from_lidar
    if planar:  # CARMEN stores x, y, yaw of the mounting only
        T_loaded, T_original = T_loaded[:2, [0, 1, 3]], T_original[:2, [0, 1, 3]]
    np.testing.assert_allclose(T_loaded, T_original, atol=1e-6)


@pytest.mark.parametrize("format", list(PRECISION))
def test_simulated_drive_round_trips(drives, format, tmp_path) -> None:
    drive = drives(format)
    written = write_simulated(drive, format, tmp_path)
    assert detect_format(tmp_path) == format
    loaded = load_log(tmp_path)
    assert loaded.source_format == format and loaded.warnings == []
    original = drive.log
    range_tol, stamp_tol = PRECISION[format]
    assert_scans_equal(loaded, original, range_tol, stamp_tol, planar=format == "carmen")
    assert loaded.vehicle.kind == original.vehicle.kind
    if original.encoders is not None:
        np.testing.assert_array_equal(loaded.encoders.ticks, original.encoders.ticks)
        np.testing.assert_allclose(loaded.encoders.t_s, original.encoders.t_s, rtol=0, atol=stamp_tol + 1e-12)
        assert loaded.vehicle.wheel_diameters_m == pytest.approx(original.vehicle.wheel_diameters_m)
        assert loaded.vehicle.ticks_per_revolution == original.vehicle.ticks_per_revolution
    if original.gyro is not None:
        np.testing.assert_allclose(loaded.gyro.t_s, original.gyro.t_s, rtol=0, atol=stamp_tol + 1e-12)
        np.testing.assert_allclose(loaded.gyro.yaw_rate_rad_s, original.gyro.yaw_rate_rad_s, rtol=0, atol=1e-5)
    if original.odometry is not None:
        np.testing.assert_allclose(loaded.odometry.poses, original.odometry.poses, rtol=0, atol=1e-6)
    truth = np.loadtxt(tmp_path / "ground_truth.txt")
    assert truth.shape == (len(original.scans), 4)
    np.testing.assert_allclose(truth[:, 0], original.scans.t_s, atol=1e-6)
    assert written.exists()


def test_thor_npz_variant_round_trips(drives, tmp_path) -> None:
    drive = drives("thor")
    thor_format.write(drive.log, tmp_path, variant="npz", set_number=21)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Encoders21.npz", "Hokuyo21.npz", "Imu21.npz"]
    loaded = load_log(tmp_path / "Hokuyo21.npz")
    assert_scans_equal(loaded, drive.log, 0.0, 0.0)
    np.testing.assert_array_equal(loaded.encoders.ticks, drive.log.encoders.ticks)


def test_car_log_written_as_drivelog_and_back_keeps_the_tilted_lidar(drives, tmp_path) -> None:
    drive = drives("ece276a-car")
    loaded = load_log(write_log(drive.log, "drivelog", tmp_path))
    assert_scans_equal(loaded, drive.log, 0.0, 0.0)
    assert loaded.vehicle.T_vehicle_from_gyro[:3, 3] == pytest.approx([-0.335, -0.035, 0.78])


def test_formats_refuse_logs_they_cannot_hold(drives, tmp_path) -> None:
    from slam_engine.errors import LogFormatError

    with pytest.raises(LogFormatError, match="four wheel encoders"):
        write_log(drives("drivelog").log, "thor", tmp_path / "a")
    with pytest.raises(LogFormatError, match="tilted LiDAR"):
        write_log(drives("ece276a-car").log, "carmen", tmp_path / "b")
    with pytest.raises(LogFormatError, match="682-beam"):
        write_log(drives("drivelog").log, "breezyslam", tmp_path / "c")
    with pytest.raises(LogFormatError, match="four wheel encoders"):
        write_simulated(drives("drivelog"), "thor", tmp_path / "d")
    # A differential robot with a gyro goes into CARMEN as dead-reckoned ODOM + ROBOTLASER1 (270 deg).
    carmen = load_log(write_simulated(drives("drivelog"), "carmen", tmp_path / "e"))
    assert carmen.lidar.num_beams == 541 and len(carmen.odometry) == len(drives("drivelog").log.encoders)
