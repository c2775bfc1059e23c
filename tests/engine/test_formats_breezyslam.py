"""BreezySLAM .dat logs: the two real Mines recordings and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.errors import LogFormatError
from slam_engine.formats import detect_format, load_log
from slam_engine.model.drive_log import MotionModelKind


@pytest.mark.parametrize(("name", "lines", "duration_s", "zero_share", "max_m", "left_ticks"), [
    ("exp1.dat", 756, 74.62, 0.525, 5.562, (29221, 211828)),
    ("exp2.dat", 641, 63.16, 0.553, 5.580, None),
])
def test_real_logs_load_with_urg04lx_geometry_and_metres(dataset, name, lines, duration_s, zero_share, max_m,
                                                         left_ticks) -> None:
    path = dataset(f"breezyslam/{name}")
    assert detect_format(path) == "breezyslam"
    log = load_log(path)
    assert len(log.scans) == lines and len(log.encoders) == lines
    assert log.lidar.num_beams == 682 and log.scans.ranges_m.shape == (lines, 682)
    assert np.degrees(log.lidar.beam_angles_rad[[0, -1]]) == pytest.approx([-119.707, 119.707], abs=1e-3)
    assert np.degrees(log.lidar.angle_increment_rad) == pytest.approx(0.3515625)
    assert log.lidar.T_vehicle_from_lidar[0, 3] == pytest.approx(0.145)
    assert np.isinf(log.scans.ranges_m).mean() == pytest.approx(zero_share, abs=0.001)
    assert log.scans.ranges_m[np.isfinite(log.scans.ranges_m)].max() == pytest.approx(max_m)
    assert log.scans.t_s[-1] - log.scans.t_s[0] == pytest.approx(duration_s, abs=0.01)
    assert log.vehicle.kind == MotionModelKind.DIFFERENTIAL
    assert log.vehicle.ticks_per_revolution == 2000 and log.vehicle.track_width_m == pytest.approx(0.33)
    if left_ticks:  # PROVENANCE: "left 29221 -> 211828" (first and largest value)
        assert (log.encoders.ticks[0, 0], log.encoders.ticks[:, 0].max()) == left_ticks
    steps = np.diff(log.encoders.ticks, axis=0)
    assert np.median(steps, axis=0) == pytest.approx([220, 220], abs=30)  # about 220 ticks per line
    assert (steps < 0).mean() < 0.07  # the robot backs up now and then: ticks are signed counts


def dat_line(t_us: int, left: int = 100, right: int = 100, range_mm: str = "1000") -> str:
    return " ".join([str(t_us), "0", str(left), str(right)] + ["0"] * 20 + [range_mm] * 682 + ["0"])


def test_bad_breezyslam_lines(tmp_path) -> None:
    path = tmp_path / "bad.dat"
    path.write_text(dat_line(1000) + "\n" + dat_line(2000)[:500] + "\n")
    with pytest.raises(LogFormatError, match="line 2: record has .* fields, expected 707"):
        load_log(path, format="breezyslam")
    path.write_text(dat_line(1000) + "\n" + dat_line(2000).replace(" 100 100 ", " 100.5 100 ", 1) + "\n")
    with pytest.raises(LogFormatError, match="line 2: wheel ticks"):
        load_log(path)
    path.write_text(dat_line(1000) + "\n" + dat_line(2000, range_mm="-5") + "\n")
    with pytest.raises(LogFormatError, match="line 2: negative range"):
        load_log(path)
    path.write_text(dat_line(1000) + "\n" + dat_line(2000, range_mm="nan") + "\n")
    with pytest.raises(LogFormatError, match="line 2: range is NaN"):
        load_log(path)
