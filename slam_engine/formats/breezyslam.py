"""BreezySLAM / CoreSLAM ``.dat`` logs (the Paris Mines rover, exp1.dat / exp2.dat).

One record per line, 707 whitespace-separated numbers: field 0 the time in microseconds, field 1
undocumented, fields 2 and 3 cumulative left and right wheel ticks, fields 4-23 other telemetry
(ignored), fields 24-705 the 682 Hokuyo URG-04LX ranges in millimetres (0 = no return), field 706
unused. The robot: differential drive, wheel radius 77 mm, axle 330 mm, 2000 ticks per wheel
revolution; the laser 145 mm ahead of the axle centre, 682 beams 360/1024 deg apart (239.7 deg,
symmetric about the front). The file holds no scan timing; the URG-04LX's specification does: 10
scans per second, 1024 steps per rotation, so consecutive beams are 0.1 / 1024 s apart and a scan's
682 beams are swept in 67 ms, counter-clockwise (``time_increment_s``, for de-skew). The stamp's
place in the sweep, and the lag of the scans behind the wheel ticks (about 0.15 s on exp2), are not
known: the engine estimates them (:mod:`slam_engine.frontend.time_offset`).

Ticks per revolution: BreezySLAM turns ticks into wheel angles as ``ticks * 180 / 2000`` degrees
(read alone: 4000 ticks per revolution), but its pose change is ``r * (phi_l + phi_r)`` forward and
``r / (axle / 2) * (phi_r - phi_l)`` turned, twice the differential-drive formulas (which halve the
first and divide the second by the whole axle). Its odometry is therefore that of 2000 ticks per
revolution, and the scans agree: matched against each other, the drives of exp1/exp2 are 1.9 times
longer, in distance and in heading change, than 4000-tick odometry says.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import clean_ranges, head_lines, is_number, open_text, time_order
from slam_engine.model.drive_log import DriveLog, EncoderStream, LidarModel, MotionModelKind, ScanStream, VehicleModel

FIELDS = 707
BEAMS = 682
FIRST_RANGE_FIELD = 24
URG_STEP_RAD = float(np.radians(360 / 1024))
URG_STEP_S = 0.1 / 1024  # 10 scans/s, 1024 steps per rotation (the sensor's specification)
MINES_ROVER = VehicleModel(kind=MotionModelKind.DIFFERENTIAL, ticks_per_revolution=2000,
                           wheel_diameters_m=(0.154, 0.154), wheel_names=("left", "right"), track_width_m=0.33,
                           name="Mines rover")


def urg_04lx(offset_m: float = 0.145, height_m: float = 0.25) -> LidarModel:
    """The Hokuyo URG-04LX as the Mines rover carries it (``offset_m`` ahead of the axle centre)."""
    T = np.eye(4)
    T[0, 3], T[2, 3] = offset_m, height_m
    return LidarModel(num_beams=BEAMS, angle_min_rad=-(BEAMS - 1) / 2 * URG_STEP_RAD,
                      angle_increment_rad=URG_STEP_RAD, range_min_m=0.02, range_max_m=5.6,
                      T_vehicle_from_lidar=T, name="Hokuyo URG-04LX", time_increment_s=URG_STEP_S)


def sniff(path: Path) -> bool:
    """Lines of exactly 707 numbers whose first is an integer microsecond stamp."""
    lines = [line.split() for line in head_lines(path, 32768) if line.strip()]
    if not lines:
        return False
    return all(len(tokens) == FIELDS for tokens in lines[:3]) and all(
        is_number(tok) for tok in lines[0]) and lines[0][0].isdigit()


def load(path: Path) -> DriveLog:
    """Read a .dat log: scans and encoder ticks share each line's stamp."""
    path = Path(path)
    rows: list[np.ndarray] = []
    line_numbers: list[int] = []
    try:
        with open_text(path) as handle:
            for line_no, line in enumerate(handle, start=1):
                tokens = line.split()
                if not tokens:
                    continue
                if len(tokens) != FIELDS:
                    raise LogFormatError(f"record has {len(tokens)} fields, expected {FIELDS} "
                                         "(truncated or not a BreezySLAM log)", path=str(path),
                                         location=f"line {line_no}")
                try:
                    rows.append(np.array(tokens[:FIRST_RANGE_FIELD + BEAMS], dtype=np.float64))
                except ValueError as error:
                    raise LogFormatError(f"not a number: {error}", path=str(path),
                                         location=f"line {line_no}") from None
                line_numbers.append(line_no)
    except (OSError, EOFError, UnicodeDecodeError) as error:
        raise LogFormatError(f"cannot read file: {error}", path=str(path)) from None
    if not rows:
        raise LogFormatError("file holds no records", path=str(path))
    data = np.array(rows)
    label = lambda i: f"line {line_numbers[i]}"  # noqa: E731
    ticks = data[:, 2:4]
    if not np.all(ticks == np.round(ticks)):
        bad = int(np.flatnonzero((ticks != np.round(ticks)).any(axis=1))[0])
        raise LogFormatError("wheel ticks (fields 2, 3) must be integers", path=str(path), location=label(bad))
    warnings: list[str] = []
    t_s = data[:, 0] * 1e-6
    order = time_order(t_s, path, "records", warnings, label)
    ranges = clean_ranges(data[:, FIRST_RANGE_FIELD:] * 1e-3, path, "ranges", location_of=label)
    return DriveLog(
        vehicle=MINES_ROVER, lidar=urg_04lx(),
        scans=ScanStream(t_s=t_s[order], ranges_m=ranges[order]),
        encoders=EncoderStream(t_s=t_s[order], ticks=ticks[order].astype(np.int64)),
        source_format="breezyslam", source_path=str(path), warnings=warnings)


MAX_STORED_RANGE_M = 1000.0  # longer ranges are written as 0, "no return" (no overflow of the mm integers)


def write(log: DriveLog, out_dir: Path, name: str = "log") -> Path:
    """Write ``out_dir/<name>.dat``: one line per scan with the wheel ticks at the scan's stamp
    (interpolated from the encoder stream when its stamps differ), ranges rounded to millimetres."""
    path = Path(out_dir) / f"{name}.dat"
    if log.scans is None or log.lidar is None or log.encoders is None:
        raise LogFormatError("BreezySLAM logs need scans and two-wheel encoders", path=str(path))
    if log.vehicle.kind != MotionModelKind.DIFFERENTIAL or log.encoders.ticks.shape[1] != 2:
        raise LogFormatError("BreezySLAM logs hold a differential-drive robot's two wheels", path=str(path))
    if log.lidar.num_beams != BEAMS:
        raise LogFormatError(f"BreezySLAM logs hold {BEAMS}-beam URG-04LX scans, not {log.lidar.num_beams}",
                             path=str(path))
    t = log.scans.t_s
    ticks = np.column_stack([np.round(np.interp(t, log.encoders.t_s, log.encoders.ticks[:, k]))
                             for k in range(2)]).astype(np.int64)
    ranges_m = np.asarray(log.scans.ranges_m, dtype=np.float64)
    storable = np.isfinite(ranges_m) & (ranges_m <= MAX_STORED_RANGE_M)  # the rest is "no return" (0)
    ranges_mm = np.round(np.where(storable, ranges_m, 0.0) * 1000.0).astype(np.int64)
    stamps_us = np.round(t * 1e6).astype(np.int64)
    filler = " ".join(["0"] * (FIRST_RANGE_FIELD - 4))
    with open(path, "w") as out:
        for k in range(len(t)):
            ranges = " ".join(map(str, ranges_mm[k].tolist()))
            out.write(f"{stamps_us[k]} 0 {ticks[k, 0]} {ticks[k, 1]} {filler} {ranges} 0\n")
    return path
