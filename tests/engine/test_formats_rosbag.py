"""ROS bags: a bare .mcap file, tf chains, REP 117 ranges, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.errors import LogFormatError, UnknownFormatError
from slam_engine.formats import detect_format, load_log, write_log
from slam_engine.simulation import simulate


@pytest.fixture(scope="module")
def drive():
    return simulate(seed=4, rig="ros-robot", max_duration_s=4.0)


def test_bare_mcap_file_and_bag_folder_load_alike(drive, tmp_path) -> None:
    folder = write_log(drive.log, "rosbag", tmp_path)
    mcap = next(folder.glob("*.mcap"))
    assert detect_format(mcap) == "rosbag" and detect_format(folder) == "rosbag"
    from_file, from_folder = load_log(mcap), load_log(folder)
    np.testing.assert_array_equal(from_file.scans.ranges_m, from_folder.scans.ranges_m)
    assert from_file.lidar.T_vehicle_from_lidar[:3, 3] == pytest.approx([0.05, 0.0, 0.25])
    assert len(from_file.odometry) == len(drive.log.odometry)


def test_rotated_tilted_lidar_mount_survives_tf_static(drive, tmp_path) -> None:
    from dataclasses import replace

    T = np.eye(4)
    angle = np.radians(30.0)
    T[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # and rolled 90 deg
    T[:3, 3] = [0.3, -0.1, 0.5]
    log = replace(drive.log, lidar=replace(drive.log.lidar, T_vehicle_from_lidar=T))
    loaded = load_log(write_log(log, "rosbag", tmp_path))
    np.testing.assert_allclose(loaded.lidar.T_vehicle_from_lidar, T, atol=1e-9)


def test_bags_without_useful_topics_and_non_bags(tmp_path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(tmp_path / "chatter", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        writer.write(conn, 1, store.serialize_cdr(store.types["std_msgs/msg/String"](data="hi"),
                                                  "std_msgs/msg/String"))
    with pytest.raises(LogFormatError, match="no LaserScan, Odometry, Imu or tf_static"):
        load_log(tmp_path / "chatter")
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 20)
    with pytest.raises(LogFormatError, match="fake.mcap"):
        load_log(fake)
    other = tmp_path / "other.bin"
    other.write_bytes(b"\x00\x01\x02")
    with pytest.raises(UnknownFormatError):
        load_log(other)


def _scan_bag(folder, scans: list[tuple[float, float, int]]):
    """A bag of LaserScans given as (angle_min, angle_increment, beams), 2 m ranges, 0.1 s apart."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    kind = "sensor_msgs/msg/LaserScan"
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/scan", kind, typestore=store)
        for k, (start, increment, beams) in enumerate(scans):
            t_ns = 1_000_000_000 + k * 100_000_000
            header = store.types["std_msgs/msg/Header"](
                stamp=store.types["builtin_interfaces/msg/Time"](sec=1, nanosec=k * 100_000_000), frame_id="laser")
            msg = store.types[kind](header=header, angle_min=start, angle_max=start + increment * (beams - 1),
                                    angle_increment=increment, time_increment=0.0, scan_time=0.0, range_min=0.1,
                                    range_max=30.0, ranges=np.full(beams, 2.0, dtype=np.float32),
                                    intensities=np.zeros(0, dtype=np.float32))
            writer.write(conn, t_ns, store.serialize_cdr(msg, kind))
    return folder


def test_laser_scans_keep_their_own_start_angle_and_beam_count(tmp_path) -> None:
    step = np.radians(0.25)
    one = np.radians(1.0)
    log = load_log(_scan_bag(tmp_path / "interlaced", [(-np.pi / 2 + (k % 4) * step, one, 181 - (k % 4 == 3))
                                                        for k in range(8)]))
    assert log.lidar.num_beams == 181
    np.testing.assert_allclose(log.scans.angle_offset_rad, [0, step, 2 * step, 3 * step] * 2, atol=1e-6)
    assert np.isinf(log.scans.ranges_m[3, 180]) and (log.scans.ranges_m[3, :180] == 2.0).all()
    with pytest.raises(LogFormatError, match="message at 1100000000 ns: scan angle_increment"):
        load_log(_scan_bag(tmp_path / "bad", [(-np.pi / 2, one, 181), (-np.pi / 2, one / 2, 361)]))
