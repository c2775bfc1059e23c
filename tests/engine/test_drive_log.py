"""DriveLog: merged message order, summaries."""

from __future__ import annotations

import numpy as np

from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    LidarModel,
    MotionModelKind,
    ScanStream,
    VehicleModel,
)
from slam_engine.model.messages import EncoderMessage, GyroMessage, ScanMessage


def make_log() -> DriveLog:
    return DriveLog(
        vehicle=VehicleModel(kind=MotionModelKind.DIFFERENTIAL, ticks_per_revolution=100,
                             wheel_diameters_m=(0.2, 0.2), wheel_names=("left", "right"), track_width_m=0.5),
        lidar=LidarModel(num_beams=3, angle_min_rad=-0.1, angle_increment_rad=0.1, range_min_m=0.1,
                         range_max_m=10.0),
        scans=ScanStream(t_s=np.array([0.5, 1.0]), ranges_m=np.ones((2, 3), np.float32)),
        encoders=EncoderStream(t_s=np.array([0.0, 0.5, 1.0]), ticks=np.array([[0, 0], [5, 6], [10, 12]])),
        gyro=GyroStream(t_s=np.array([0.25, 0.75]), yaw_rate_rad_s=np.array([0.1, 0.2])),
        source_format="test",
    )


def test_messages_are_time_ordered_with_odometry_before_scans_at_equal_stamps() -> None:
    kinds = [(type(m).__name__, m.t_s) for m in make_log().messages()]
    assert kinds == [
        ("EncoderMessage", 0.0), ("GyroMessage", 0.25), ("EncoderMessage", 0.5), ("ScanMessage", 0.5),
        ("GyroMessage", 0.75), ("EncoderMessage", 1.0), ("ScanMessage", 1.0),
    ]


def test_message_payloads_come_from_their_rows() -> None:
    msgs = list(make_log().messages())
    enc = [m for m in msgs if isinstance(m, EncoderMessage)]
    assert enc[2].ticks.tolist() == [10, 12]
    gyro = [m for m in msgs if isinstance(m, GyroMessage)]
    assert gyro[1].yaw_rate_rad_s == 0.2
    assert all(isinstance(m.ranges_m, np.ndarray) for m in msgs if isinstance(m, ScanMessage))


def test_summary_counts_streams_and_span() -> None:
    summary = make_log().summary()
    assert summary["streams"] == {"scans": 2, "encoders": 3, "gyro": 2}
    assert summary["time_span_s"] == [0.0, 1.0]
    assert summary["lidar_beams"] == 3
    assert summary["vehicle"] == "differential"


def test_beam_angles() -> None:
    np.testing.assert_allclose(make_log().lidar.beam_angles_rad, [-0.1, 0.0, 0.1])


def test_first_beyond_finds_the_first_bad_value_across_blocks(monkeypatch) -> None:
    """Checked in blocks of rows (a map bundle's 1.6 GB array must not be copied whole, as float64 and
    again for its absolute values): the flat index is the same as over the whole array."""
    from slam_engine.model import drive_log

    monkeypatch.setattr(drive_log, "CHECK_BLOCK_VALUES", 8)  # 4 rows of 2 per block
    values = np.zeros((10, 2), np.float32)
    assert drive_log.first_beyond(values, 1.0) is None and drive_log.first_beyond(values, np.inf) is None
    values[6, 1] = 5.0
    assert drive_log.first_beyond(values, 1.0) == 13 and drive_log.first_beyond(values, np.inf) is None
    values[9, 0] = np.inf
    assert drive_log.first_beyond(values, np.inf) == 18  # an inf limit: the first value not finite
    values[1, 0] = np.nan
    assert drive_log.first_beyond(values, 1.0) == 2 and drive_log.first_beyond(values, np.inf) == 2
    assert drive_log.first_beyond(np.float64(3.0), 1.0) == 0 and drive_log.first_beyond(np.zeros(0), 1.0) is None
    assert drive_log.first_beyond(values[:, 1], 1.0) == 6  # a strided column
