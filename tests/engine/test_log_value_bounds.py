"""Values no real drive holds are refused at load time, naming the record and the value (issue 41,
item 9): ODOM at +-1.7e308 failed a job with "internal error: SystemError: CPUDispatcher(...)", a FLASER
pose at 1.7e308 with "ValueError: Maximum allowed dimension exceeded"; both were accepted at upload."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from lidarmap.cli import app
from slam_engine.errors import LogFormatError
from slam_engine.formats import load_log, write_log
from slam_engine.simulation import simulate, write_simulated


@pytest.fixture(scope="module")
def carmen_lines(tmp_path_factory) -> list[str]:
    drive = simulate("office", seed=1, rig="carmen-robot", max_duration_s=4.0)
    return write_simulated(drive, "carmen", tmp_path_factory.mktemp("sim")).read_text().splitlines()


def with_field(lines: list[str], kind: str, field: int, value: str) -> tuple[list[str], int]:
    """``lines`` with field ``field`` (0 = the keyword) of the third ``kind`` record set to ``value``, and
    that record's line number (1-based)."""
    hits = [i for i, line in enumerate(lines) if line.startswith(kind + " ")]
    index = hits[2]
    tokens = lines[index].split()
    tokens[field] = value
    return [*lines[:index], " ".join(tokens), *lines[index + 1:]], index + 1


def flaser_field(lines: list[str], offset_after_ranges: int) -> int:
    """Index of a FLASER field counted after its ranges (0 = laser x, 3 = robot x, 6 = timestamp)."""
    n = int(next(line for line in lines if line.startswith("FLASER ")).split()[1])
    return 2 + n + offset_after_ranges


@pytest.mark.parametrize(("kind", "field", "value", "message"), [
    ("ODOM", 1, "1.7e308", "ODOM pose is 1.7e+308 m, beyond +-1e+06 m"),
    ("ODOM", 2, "-1.7e308", "ODOM pose is -1.7e+308 m, beyond +-1e+06 m"),
    ("ODOM", 3, "1e300", "ODOM pose is 1e+300 rad, beyond +-1e+06 rad"),
    ("ODOM", 7, "1e300", "timestamp is 1e+300 s, beyond +-1e+10 s"),
    ("FLASER", "robot x", "1.7e308", "robot pose is 1.7e+308 m, beyond +-1e+06 m"),
    ("FLASER", "laser y", "-2e6", "laser pose is -2e+06 m, beyond +-1e+06 m"),
    ("FLASER", "time", "1e300", "timestamp is 1e+300 s, beyond +-1e+10 s"),
    ("FLASER", 5, "1e300", "range 1e+300 m at beam 3 is beyond 1e+06 m"),
])
def test_absurd_carmen_values_name_the_line_and_the_value(tmp_path, carmen_lines, kind, field, value,
                                                          message) -> None:
    named = {"robot x": 3, "laser y": 1, "time": 6}
    index = flaser_field(carmen_lines, named[field]) if isinstance(field, str) else field
    lines, line_no = with_field(carmen_lines, kind, index, value)
    path = tmp_path / "bad.clf"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError) as caught:
        load_log(path)
    assert caught.value.location == f"line {line_no}", caught.value
    assert message in caught.value.message, caught.value.message
    # the CLI: exit code 2 and one line naming the file, the line and the value
    result = CliRunner().invoke(app, ["run", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    shown = result.stderr.strip().splitlines()
    assert len(shown) == 1 and f"line {line_no}" in shown[0] and message in shown[0], shown
    assert not re.search(r"0x[0-9a-f]{6,}", shown[0])


def test_a_format_without_lines_names_the_stream_record(tmp_path) -> None:
    log = simulate("office", seed=1, rig="robot", max_duration_s=4.0).log
    assert log.odometry is not None or log.encoders is not None
    source = write_log(log, "drivelog", tmp_path / "good")
    load_log(source).check_values()  # a real (simulated) drive passes
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 1.7e308, 0.0]])
    from slam_engine.model.drive_log import OdometryStream

    log.odometry = OdometryStream(t_s=np.array([0.0, 1.0]), poses=poses)
    with pytest.raises(LogFormatError, match=r"odometry position is 1\.7e\+308 m") as caught:
        log.check_values()
    assert caught.value.location == "odometry record 1"


def test_real_magnitudes_pass(tmp_path: Path, carmen_lines) -> None:
    # a drive 900 km from its origin, headings unwrapped to 1000 rad: unusual but real
    lines, _ = with_field(carmen_lines, "ODOM", 1, "900000.0")
    lines, _ = with_field(lines, "ODOM", 3, "1000.0")
    path = tmp_path / "far.clf"
    path.write_text("\n".join(lines) + "\n")
    assert load_log(path).odometry is not None
