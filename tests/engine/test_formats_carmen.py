"""CARMEN logs: the real benchmark and Malaga logs, the new-format records, round trips, bad input."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from slam_engine.errors import LogFormatError, UnknownFormatError
from slam_engine.formats import detect_format, list_formats, load_log, write_log
from slam_engine.model.drive_log import MotionModelKind


@pytest.mark.parametrize(("name", "scans", "beams", "increment_deg", "inf_share"), [
    ("benchmark/intel.clf", 910, 180, 1.0, (0.02, 0.03)),
    ("benchmark/freiburg-079.clf", 4791, 360, 0.5, (0.015, 0.03)),
])
def test_benchmark_logs_load_with_their_geometry(dataset, name, scans, beams, increment_deg, inf_share) -> None:
    path = dataset(name)
    assert detect_format(path) == "carmen"
    log = load_log(path)
    assert log.vehicle.kind == MotionModelKind.ODOMETRY
    assert len(log.scans) == scans and len(log.odometry) == scans
    assert log.scans.ranges_m.shape == (scans, beams)
    assert log.lidar.num_beams == beams
    assert np.degrees(log.lidar.angle_min_rad) == pytest.approx(-90.0)
    assert np.degrees(log.lidar.angle_increment_rad) == pytest.approx(increment_deg)
    np.testing.assert_allclose(log.lidar.T_vehicle_from_lidar, np.eye(4))
    share = np.isinf(log.scans.ranges_m).mean()
    assert inf_share[0] < share < inf_share[1]  # the 81.83 / 81.91 m no-return readings
    assert np.all(log.scans.ranges_m[np.isfinite(log.scans.ranges_m)] < 40.0)
    assert np.all(np.diff(log.scans.t_s) > 0)
    assert log.warnings == []


def test_intel_first_record_values(dataset) -> None:
    log = load_log(dataset("benchmark/intel.clf"))
    assert log.scans.t_s[0] == pytest.approx(32.9068)
    assert log.scans.ranges_m[0, :3] == pytest.approx([1.09, 1.08, 1.08])
    assert log.odometry.poses[0] == pytest.approx([0.600266, -0.032033, -0.354665])


def test_malaga_laser_offset_and_361_beams(dataset) -> None:
    path = next(dataset("malaga").glob("*.clf"))
    log = load_log(path)
    assert len(log.scans) == 225 and log.lidar.num_beams == 361
    assert np.degrees(log.lidar.beam_angles_rad[[0, 180, 360]]) == pytest.approx([-90.0, 0.0, 90.0])
    assert log.lidar.T_vehicle_from_lidar[:3, 3] == pytest.approx([0.78, 0.0, 0.0])
    finite = log.scans.ranges_m[np.isfinite(log.scans.ranges_m)]
    assert finite.min() > 0.78 and finite.max() < 60.0
    assert np.isinf(log.scans.ranges_m).mean() == pytest.approx(0.115, abs=0.005)
    assert log.time_span_s()[1] - log.time_span_s()[0] == pytest.approx(59.07, abs=0.01)
    steps = np.hypot(*np.diff(log.odometry.poses[:, :2], axis=0).T)
    assert steps.sum() == pytest.approx(76.4, abs=0.1)  # PROVENANCE: dead-reckoned path 76.4 m


def test_carmen_round_trip_keeps_streams_within_text_precision(dataset, tmp_path) -> None:
    log = load_log(dataset("benchmark/intel.clf"))
    written = write_log(log, "carmen", tmp_path)
    again = load_log(written)
    np.testing.assert_allclose(again.scans.t_s, log.scans.t_s, atol=1e-6)
    np.testing.assert_array_equal(np.isinf(again.scans.ranges_m), np.isinf(log.scans.ranges_m))
    finite = np.isfinite(log.scans.ranges_m)
    np.testing.assert_allclose(again.scans.ranges_m[finite], log.scans.ranges_m[finite], atol=5e-4)
    np.testing.assert_allclose(again.odometry.poses, log.odometry.poses, atol=1e-6)
    assert again.lidar.angle_increment_rad == pytest.approx(log.lidar.angle_increment_rad)


def test_gzipped_log_and_robotlaser_without_odom_lines(tmp_path) -> None:
    ranges = " ".join(["1.0"] * 9 + ["30.0"])
    lines = ["PARAM robot_frontlaser_offset 0.25 host 0"]
    for k in range(3):
        t = 10.0 + 0.1 * k
        lines.append(f"ROBOTLASER1 0 -0.785398 1.570796 0.174533 30.0 0.01 0 10 {ranges} 0 "
                     f"{0.25 + 0.1 * k} 0 0 {0.1 * k} 0 0 0 0 0 0 0 {t} host {t}")
    path = tmp_path / "small.clf.gz"
    path.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode()))
    assert detect_format(path) == "carmen"
    log = load_log(path)
    assert log.lidar.num_beams == 10
    assert np.degrees(log.lidar.angle_min_rad) == pytest.approx(-45.0)
    assert np.degrees(log.lidar.angle_increment_rad) == pytest.approx(10.0)
    assert np.isinf(log.scans.ranges_m[:, 9]).all() and (log.scans.ranges_m[:, :9] == 1.0).all()
    assert log.lidar.T_vehicle_from_lidar[0, 3] == pytest.approx(0.25)
    assert log.odometry.poses[:, 0] == pytest.approx([0.0, 0.1, 0.2])
    assert any("robot poses" in w for w in log.warnings)


FLASER = "FLASER 4 1.0 2.0 3.0 4.0 0 0 0 0 0 0 {t} host {t}"


def write_clf(tmp_path, *lines: str):
    path = tmp_path / "bad.clf"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_truncated_line_names_the_line(tmp_path) -> None:
    path = write_clf(tmp_path, FLASER.format(t=1.0), "FLASER 4 1.0 2.0 3.0")
    with pytest.raises(LogFormatError, match="line 2.*fields, expected 15"):
        load_log(path)


def test_nan_and_negative_ranges_are_refused(tmp_path) -> None:
    path = write_clf(tmp_path, FLASER.format(t=1.0), FLASER.format(t=2.0).replace("2.0 3.0", "nan 3.0", 1))
    with pytest.raises(LogFormatError, match="line 2: range is NaN"):
        load_log(path)
    path = write_clf(tmp_path, FLASER.format(t=1.0).replace("3.0", "-3.0", 1))
    with pytest.raises(LogFormatError, match="line 1: negative range -3.0 at beam 2"):
        load_log(path)


def test_a_few_shuffled_stamps_are_sorted_with_a_warning(tmp_path) -> None:
    stamps = [float(k) for k in range(20)]
    stamps[5], stamps[6] = stamps[6], stamps[5]
    path = write_clf(tmp_path, *[FLASER.format(t=t) for t in stamps] + [FLASER.format(t=19.0)])
    log = load_log(path)
    assert np.all(np.diff(log.scans.t_s) > 0) and len(log.scans) == 20
    assert any("out of time order" in w for w in log.warnings)
    assert any("repeat an earlier timestamp" in w for w in log.warnings)


def test_mostly_backward_stamps_are_refused(tmp_path) -> None:
    path = write_clf(tmp_path, *[FLASER.format(t=t) for t in (5.0, 4.0, 3.0, 2.0, 1.0)])
    with pytest.raises(LogFormatError, match="not in time order"):
        load_log(path)


def test_unknown_record_and_unknown_content(tmp_path) -> None:
    path = write_clf(tmp_path, FLASER.format(t=1.0), "WOBBLE 1 2 3")
    with pytest.raises(LogFormatError, match="line 2: unknown CARMEN record type 'WOBBLE'"):
        load_log(path, format="carmen")
    other = tmp_path / "notes.txt"
    other.write_text("hello world\n")
    with pytest.raises(UnknownFormatError):
        load_log(other)
    with pytest.raises(UnknownFormatError, match="unknown format 'nope'"):
        load_log(other, format="nope")
    with pytest.raises(LogFormatError, match="no such file"):
        load_log(tmp_path / "missing.clf")


def test_registry_lists_every_format() -> None:
    names = [f.name for f in list_formats()]
    assert names == ["carmen", "breezyslam", "thor", "ece276a-car", "rosbag", "drivelog"]
    assert all(f.can_write for f in list_formats())


def _interlaced_line(k: int, t: float, start_deg: float, n: int, resolution_deg: float = 1.0) -> str:
    ranges = " ".join(f"{2.0 + 0.01 * i:.2f}" for i in range(n))
    return (f"ROBOTLASER1 0 {np.radians(start_deg):.9f} {np.radians(180.0):.9f} {np.radians(resolution_deg):.12f} "
            f"80.0 0.01 0 {n} {ranges} 0 {0.1 * k} 0 0 {0.1 * k} 0 0 0 0 0 0 0 {t} host {t}")


def test_interlaced_robotlaser_carries_each_scans_start_angle_and_beam_count(tmp_path) -> None:
    # an interlaced SICK: four start angles 0.25 deg apart, cycling; 181 beams, or 180 for the last phase
    starts = [-90.0, -89.75, -89.5, -89.25]
    lines = [_interlaced_line(k, 1.0 + 0.1 * k, starts[k % 4], 180 if k % 4 == 3 else 181) for k in range(8)]
    log = load_log(write_clf(tmp_path, *lines))
    assert log.lidar.num_beams == 181
    assert np.degrees(log.lidar.angle_min_rad) == pytest.approx(-90.0)
    assert np.degrees(log.scans.angle_offset_rad) == pytest.approx([0.0, 0.25, 0.5, 0.75] * 2)
    assert log.scans.ranges_m.shape == (8, 181)
    assert np.isinf(log.scans.ranges_m[3, 180]) and log.scans.ranges_m[3, 179] == pytest.approx(3.79)
    assert np.isfinite(log.scans.ranges_m[[0, 1, 2, 4, 5, 6]]).all()
    assert any("carried per scan" in w for w in log.warnings)
    messages = [m for m in log.messages() if hasattr(m, "ranges_m")]
    assert np.degrees([m.angle_offset_rad for m in messages]) == pytest.approx([0.0, 0.25, 0.5, 0.75] * 2)


def test_interlaced_log_round_trips_through_robotlaser1(tmp_path) -> None:
    starts = [-90.0, -89.75, -89.5, -89.25]
    lines = [_interlaced_line(k, 1.0 + 0.1 * k, starts[k % 4], 181) for k in range(8)]
    log = load_log(write_clf(tmp_path, *lines))
    written = write_log(log, "carmen", tmp_path / "out")
    assert "\nROBOTLASER1 " in written.read_text() and "\nFLASER " not in written.read_text()
    again = load_log(written)
    np.testing.assert_allclose(again.scans.angle_offset_rad, log.scans.angle_offset_rad, atol=1e-8)
    np.testing.assert_allclose(again.scans.ranges_m, log.scans.ranges_m, atol=1e-3)


def test_fixed_geometry_has_no_per_scan_offsets(tmp_path) -> None:
    lines = [_interlaced_line(k, 1.0 + 0.1 * k, -90.0, 181) for k in range(4)]
    log = load_log(write_clf(tmp_path, *lines))
    assert log.scans.angle_offset_rad is None
    assert not any("carried per scan" in w for w in log.warnings)


def test_a_changing_resolution_is_refused_naming_the_line(tmp_path) -> None:
    lines = [_interlaced_line(0, 1.0, -90.0, 181), _interlaced_line(1, 1.1, -90.0, 361, resolution_deg=0.5)]
    with pytest.raises(LogFormatError, match="line 2: laser resolution changes"):
        load_log(write_clf(tmp_path, *lines))


def test_flaser_beam_count_may_change_when_the_spacing_does_not(tmp_path) -> None:
    f181 = "FLASER 181 " + " ".join(["2.0"] * 181) + " 0 0 0 0 0 0 {t} host {t}"
    f180 = "FLASER 180 " + " ".join(["2.0"] * 180) + " 0 0 0 0 0 0 {t} host {t}"
    log = load_log(write_clf(tmp_path, f181.format(t=1.0), f180.format(t=2.0)))
    assert log.lidar.num_beams == 181 and log.scans.angle_offset_rad is None
    assert np.isinf(log.scans.ranges_m[1, 180]) and np.isfinite(log.scans.ranges_m[1, :180]).all()
    f361 = "FLASER 361 " + " ".join(["2.0"] * 361) + " 0 0 0 0 0 0 {t} host {t}"
    with pytest.raises(LogFormatError, match="line 2: FLASER beam spacing changes"):
        load_log(write_clf(tmp_path, f181.format(t=1.0), f361.format(t=2.0)))


def _flaser(pose: tuple[float, float, float], t_s: float, ranges: str = "1.0 2.0 3.0 4.0") -> str:
    x, y, th = pose
    return f"FLASER 4 {ranges} {x} {y} {th} {x} {y} {th} {t_s} host {t_s}\n"


def test_each_scan_pairs_with_the_odometry_its_own_record_carries(tmp_path) -> None:
    """Real Intel: ODOM records interpolated at a scan's (late, jittered) stamp put 154 scans more than
    0.1 rad off the pose their FLASER record carries. The scan's own pose is the one it was taken at."""
    lines = [f"ODOM {0.1 * k} 0 {0.2 * k} 0 0 0 {float(k)} host {float(k)}\n" for k in range(10)]
    lines += [_flaser((0.1 * k, 0.0, 0.2 * k), float(k)) for k in range(9)]
    # scan 6 was taken at 6.0 s but stamped 6.4 s: the ODOM records there say heading 1.28, not 1.2
    lines[10 + 6] = _flaser((0.6, 0.0, 1.2), 6.4)
    (tmp_path / "jitter.clf").write_text("".join(lines))
    log = load_log(tmp_path / "jitter.clf")
    from slam_engine.model.poses import interpolate

    at_scans = interpolate(log.odometry.t_s, log.odometry.poses, log.scans.t_s)
    np.testing.assert_allclose(at_scans[:, 2], [0.2 * k for k in range(9)], atol=1e-9)
    np.testing.assert_allclose(at_scans[6], [0.6, 0.0, 1.2], atol=1e-9)
    assert len(log.odometry) == 11  # the ODOM records, and scan 6's own pose at 6.4 s
    assert any("at 1 of 9 FLASER records" in w and "own record's pose" in w for w in log.warnings)


def test_agreeing_odom_and_laser_poses_keep_the_odom_stream(tmp_path) -> None:
    lines = [f"ODOM {0.1 * k} 0 0 0 0 0 {float(k)} host {float(k)}\n" for k in range(10)]
    lines += [_flaser((0.1 * k + 0.05, 0.0, 0.0), k + 0.5) for k in range(9)]
    (tmp_path / "agree.clf").write_text("".join(lines))
    log = load_log(tmp_path / "agree.clf")
    assert len(log.odometry) == 10 and log.warnings == []


def test_odometry_that_advances_while_backing_up_is_taken_backwards(tmp_path) -> None:
    """The original Freiburg 079 log: where its ODOM records read tv -0.5 m/s, their poses advance
    forward along the heading (392 records, 0.3-0.65 m per key frame off the truth). The steps are
    taken backwards, and each scan's own record pose is carried along with them."""
    lines = [f"ODOM {0.1 * k} 0 0 0.5 0 0 {float(k)} host {float(k)}\n" for k in range(5)]
    # backing up from x = 0.4 at 0.5 m/s, but the poses go on forward
    lines += [f"ODOM {0.4 + 0.1 * k} 0 0 -0.5 0 0 {4.0 + k} host {4.0 + k}\n" for k in range(1, 5)]
    lines += [_flaser((0.4 + 0.1 * k, 0.0, 0.0), 4.0 + k) for k in range(1, 5)]
    (tmp_path / "reverse.clf").write_text("".join(lines))
    log = load_log(tmp_path / "reverse.clf")
    np.testing.assert_allclose(log.odometry.poses[:, 0], [0.0, 0.1, 0.2, 0.3, 0.4, 0.3, 0.2, 0.1, 0.0], atol=1e-9)
    assert any("at 4 ODOM records the robot backs up" in w for w in log.warnings)
    from slam_engine.model.poses import interpolate

    at_scans = interpolate(log.odometry.t_s, log.odometry.poses, log.scans.t_s)
    np.testing.assert_allclose(at_scans[:, 0], [0.3, 0.2, 0.1, 0.0], atol=1e-9)
