"""CARMEN text logs (.clf / .log, optionally gzipped).

Records read (one per line, whitespace separated, ``#`` comments):

- ``PARAM name value [host ts]`` — ``robot_frontlaser_offset`` / ``_side_offset`` /
  ``_angular_offset`` (rear: ``robot_rearlaser_*``) place the LiDAR in the robot frame;
  ``robot_front_laser_max`` (``robot_rear_laser_max``) is the no-return range.
- ``ODOM x y theta tv rv accel ts host logger_ts`` — robot odometry pose [m, m, rad].
- ``FLASER n r1..rn lx ly ltheta x y theta ts host logger_ts`` (old format; ``RLASER`` for the rear
  laser): 180 deg counter-clockwise from -90 deg; beam i at -90 deg + i * 180/n for even n and
  -90 deg + i * 180/(n-1) for odd n (e.g. 361 beams 0.5 deg apart). ``lx ly ltheta`` is the laser's
  pose, ``x y theta`` the robot's odometry pose at the scan.
- ``ROBOTLASER1|2 type start_angle fov resolution max_range accuracy remission_mode n r1..rn m
  rem1..remm lx ly ltheta x y theta tv rv forward_safety side_safety turn_axis ts host logger_ts``.
- ``RAWLASER1..4 type start_angle fov resolution max_range accuracy remission_mode n r1..rn m
  rem1..remm ts host logger_ts`` (no poses).

Ranges are metres; ranges at or above the no-return range (``robot_front_laser_max``, the
ROBOTLASER/RAWLASER ``max_range`` field, else 80 m), zero, and a saturation value that fills many
beams (e.g. 50 m) become ``inf``. Only one laser is loaded (ROBOTLASER1, FLASER, RAWLASER1, ...
whichever comes first in that order); the others are reported in the log's warnings.

Odometry: the ``ODOM`` records, and where the loaded laser's records carry the robot's odometry pose
(FLASER, ROBOTLASER), each scan is paired with the pose its own record carries: where the ODOM records
interpolated at the scan's timestamp disagree with it, that pose is put into the odometry stream at the
scan's stamp (logs whose records agree, as every log lidarmap writes, keep their ODOM stream as it is).
The logger wrote that pose for the scan; the records' timestamps are when a process received them. On
the original Intel Research Lab log the two disagree: interpolated at the scan's timestamp, the ODOM
records put 154 of 13 631 scans more than 0.1 rad (up to 0.9 rad) off the pose the scan was taken at,
and the map built on them broke (docs/engine.md, "Odometry of a scan").

An ODOM step whose record says the robot backs up (``tv`` < 0) while its pose advances forward is taken
backwards (the odometry was integrated with the speed's magnitude): the original Freiburg 079 log does
so at 392 records, each key frame 0.3-0.65 m off while the robot reverses.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import clean_ranges, head_lines, is_number, open_text, time_order
from slam_engine.frontend.odometry import odometry_poses
from slam_engine.model.drive_log import (
    MAX_ANGLE_RAD,
    MAX_COORDINATE_M,
    DriveLog,
    LidarModel,
    MotionModelKind,
    OdometryStream,
    ScanStream,
    VehicleModel,
)
from slam_engine.model.poses import (
    compose,
    interpolate,
    is_planar_4x4,
    planar_from_4x4,
    relative,
    to_matrix_4x4,
    wrap_angle,
)

DEFAULT_NO_RETURN_M = 80.0
# A single range value filling this share of all beams, at >= SATURATION_MIN_M, is a no-return code.
SATURATION_SHARE = 0.005
SATURATION_MIN_M = 20.0
_LASER_PREFERENCE = ("ROBOTLASER1", "FLASER", "RAWLASER1", "ROBOTLASER2", "RLASER",
                     "RAWLASER2", "RAWLASER3", "RAWLASER4")
_KNOWN = {"PARAM", "ODOM", "TRUEPOS", "SYNC", "NMEA-GGA", "NMEA-RMC", "SONAR", "BUMPER", "IMU", "GPS",
          "POSITIONLASER", "VECTORMOVE", "ROBOTVELOCITY", "ARMSTATE", "FLASER", "RLASER", "LASER3", "LASER4",
          "ROBOTLASER1", "ROBOTLASER2", "RAWLASER1", "RAWLASER2", "RAWLASER3", "RAWLASER4", "SCANMARK",
          "POSITION"}


def _doubles() -> array:
    return array("d")


def _integers() -> array:
    return array("q")


@dataclass
class _Laser:
    """The records of one laser channel as read, packed: a record costs its numbers' bytes, not a Python
    object per value (a million beamless records took 780 MB as lists of arrays and tuples, 90 MB so)."""

    t: array = field(default_factory=_doubles)
    ranges: array = field(default_factory=_doubles)  # every record's ranges, one record after the other
    counts: array = field(default_factory=_integers)  # each record's beam count
    laser_pose: array = field(default_factory=_doubles)  # x, y, theta of each record, one after the other
    robot_pose: array = field(default_factory=_doubles)  # likewise
    lines: array = field(default_factory=_integers)
    geometry: tuple[float, float, float] | None = None  # (start angle, resolution, max range) of the first record
    starts: array = field(default_factory=_doubles)  # each record's start angle [rad] (ROBOTLASER/RAWLASER)
    increments: array = field(default_factory=_doubles)  # each FLASER record's beam spacing [rad]

    def add(self, ranges: np.ndarray, line_no: int, poses: np.ndarray | None = None) -> None:
        """One record's ranges and line (and its laser and robot poses, six numbers)."""
        self.ranges.frombytes(np.ascontiguousarray(ranges, dtype=np.float64).tobytes())
        self.counts.append(len(ranges))
        self.lines.append(line_no)
        if poses is not None:
            self.laser_pose.frombytes(np.ascontiguousarray(poses[0:3], dtype=np.float64).tobytes())
            self.robot_pose.frombytes(np.ascontiguousarray(poses[3:6], dtype=np.float64).tobytes())

    def robot_poses(self) -> np.ndarray:
        """(N, 3) the records' robot poses."""
        return np.frombuffer(self.robot_pose, dtype=np.float64).reshape(-1, 3)


def sniff(path: Path) -> bool:
    """A CARMEN log: the first records are known CARMEN keywords followed by numbers."""
    records = [line.split() for line in head_lines(path, 16384) if line.strip() and not line.startswith("#")]
    if not records:
        return False
    checked = records[:20]
    return all(r[0] in _KNOWN for r in checked) and any(
        r[0] in _KNOWN - {"PARAM"} and len(r) > 4 and is_number(r[1]) for r in checked)


def _floats(tokens: list[str], path: Path, line_no: int) -> np.ndarray:
    try:
        return np.array(tokens, dtype=np.float64)
    except ValueError as error:
        raise LogFormatError(f"not a number: {error}", path=str(path), location=f"line {line_no}") from None


def _finite(values: np.ndarray, what: str, path: Path, line_no: int) -> np.ndarray:
    """``values`` (poses, stamps, geometry) when all finite; otherwise a LogFormatError."""
    if not np.isfinite(values).all():
        raise LogFormatError(f"{what} is not finite: {' '.join(str(v) for v in values)}", path=str(path),
                             location=f"line {line_no}")
    return values


def _plausible_pose(pose: np.ndarray, what: str, path: Path, line_no: int) -> None:
    """A LogFormatError naming the line when an (x, y, theta) pose is beyond the bounds of a real drive."""
    for value, limit, unit in ((pose[0], MAX_COORDINATE_M, "m"), (pose[1], MAX_COORDINATE_M, "m"),
                               (pose[2], MAX_ANGLE_RAD, "rad")):
        if not abs(value) <= limit:
            raise LogFormatError(f"{what} is {value:g} {unit}, beyond +-{limit:g} {unit}: not a real pose",
                                 path=str(path), location=f"line {line_no}")


def _int_field(token: str, path: Path, line_no: int, what: str) -> int:
    try:
        value = int(token)
    except ValueError:
        raise LogFormatError(f"{what} is not an integer: {token!r}", path=str(path),
                             location=f"line {line_no}") from None
    if value < 0:
        raise LogFormatError(f"{what} is negative: {value}", path=str(path), location=f"line {line_no}")
    return value


def _expect_length(tokens: list[str], expected: int, path: Path, line_no: int) -> None:
    if len(tokens) != expected:
        raise LogFormatError(f"{tokens[0]} record has {len(tokens)} fields, expected {expected} "
                             "(truncated or malformed line)", path=str(path), location=f"line {line_no}")


def _parse_old_laser(tokens: list[str], laser: _Laser, path: Path, line_no: int) -> None:
    n = _int_field(tokens[1], path, line_no, "beam count") if len(tokens) > 1 else 0
    _expect_length(tokens, n + 11, path, line_no)
    values = _floats(tokens[2:n + 8], path, line_no)
    _finite(values[n:], "laser/robot pose", path, line_no)
    _plausible_pose(values[n:n + 3], "laser pose", path, line_no)
    _plausible_pose(values[n + 3:n + 6], "robot pose", path, line_no)
    if n and laser.increments and abs(_flaser_increment(n) - laser.increments[0]) > 1e-9:
        raise LogFormatError(f"{tokens[0]} beam spacing changes within the log ({n} beams over 180 deg, "
                             f"{laser.counts[0]} before)", path=str(path), location=f"line {line_no}")
    laser.increments.append(_flaser_increment(n) if n else 0.0)
    laser.t.append(float(_finite(_floats([tokens[n + 8]], path, line_no), "timestamp", path, line_no)[0]))
    laser.add(values[:n], line_no, values[n:n + 6])


def _parse_new_laser(tokens: list[str], laser: _Laser, path: Path, line_no: int, with_poses: bool) -> None:
    if len(tokens) < 10:
        _expect_length(tokens, 10, path, line_no)
    header = _finite(_floats(tokens[2:6], path, line_no), "laser geometry", path, line_no)
    n = _int_field(tokens[8], path, line_no, "beam count")
    if len(tokens) < 10 + n:
        _expect_length(tokens, 10 + n, path, line_no)
    m = _int_field(tokens[9 + n], path, line_no, "remission count")
    tail = 11 + 3 if with_poses else 3
    _expect_length(tokens, 10 + n + m + tail, path, line_no)
    ranges = _floats(tokens[9:9 + n], path, line_no)
    rest = _finite(_floats(tokens[10 + n + m:-2], path, line_no), "pose / timestamp", path, line_no)
    if with_poses:
        _plausible_pose(rest[0:3], "laser pose", path, line_no)
        _plausible_pose(rest[3:6], "robot pose", path, line_no)
    laser.add(ranges, line_no, rest[0:6] if with_poses else None)
    laser.t.append(float(rest[-1]))
    start, _fov, resolution, max_range = (float(v) for v in header)
    if not abs(start) <= 2 * np.pi:
        raise LogFormatError(f"start angle is {start:g} rad, beyond +-2 pi", path=str(path),
                             location=f"line {line_no}")
    if laser.geometry is None:
        laser.geometry = (start, resolution, max_range)
    elif abs(resolution - laser.geometry[1]) > 1e-9:
        # a start angle or beam count may change from scan to scan (interlacing, firmware modes); the
        # beam spacing may not
        raise LogFormatError(f"laser resolution changes within the log: {resolution:g} rad, "
                             f"{laser.geometry[1]:g} rad before", path=str(path), location=f"line {line_no}")
    laser.starts.append(start)


def _flaser_increment(n: int) -> float:
    """FLASER beam spacing [rad] of ``n`` beams over 180 deg."""
    return np.pi / (n - 1) if n % 2 == 1 and n > 1 else np.pi / n


def load(path: Path, no_return_m: float | None = None) -> DriveLog:
    """Read a CARMEN log into a DriveLog with an odometry stream and one laser's scans."""
    path = Path(path)
    params: dict[str, str] = {}
    odom_t, odom_tv, odom_poses, odom_lines = _doubles(), _doubles(), _doubles(), _integers()  # packed, as _Laser
    lasers: dict[str, _Laser] = {}
    skipped: dict[str, int] = {}
    try:
        with open_text(path) as handle:
            for line_no, line in enumerate(handle, start=1):
                tokens = line.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                kind = tokens[0]
                if kind == "PARAM":
                    if len(tokens) < 3:
                        raise LogFormatError("PARAM record needs a name and a value", path=str(path),
                                             location=f"line {line_no}")
                    params[tokens[1]] = tokens[2]
                elif kind == "ODOM":
                    _expect_length(tokens, 10, path, line_no)
                    values = _finite(_floats(tokens[1:8], path, line_no), "ODOM pose / velocity / time",
                                     path, line_no)
                    _plausible_pose(values[:3], "ODOM pose", path, line_no)
                    odom_poses.frombytes(values[:3].tobytes())
                    odom_tv.append(float(values[3]))
                    odom_t.append(float(values[6]))
                    odom_lines.append(line_no)
                elif kind in ("FLASER", "RLASER"):
                    _parse_old_laser(tokens, lasers.setdefault(kind, _Laser()), path, line_no)
                elif kind in ("ROBOTLASER1", "ROBOTLASER2"):
                    _parse_new_laser(tokens, lasers.setdefault(kind, _Laser()), path, line_no, with_poses=True)
                elif kind.startswith("RAWLASER") and kind in _KNOWN:
                    _parse_new_laser(tokens, lasers.setdefault(kind, _Laser()), path, line_no, with_poses=False)
                elif kind in _KNOWN:
                    skipped[kind] = skipped.get(kind, 0) + 1
                else:
                    raise LogFormatError(f"unknown CARMEN record type {kind!r}", path=str(path),
                                         location=f"line {line_no}")
    except (OSError, EOFError) as error:
        raise LogFormatError(f"cannot read file: {error}", path=str(path)) from None
    except UnicodeDecodeError as error:
        raise LogFormatError(f"not a text file: {error}", path=str(path)) from None

    warnings: list[str] = []
    if skipped:
        listed = ", ".join(f"{k} x{v}" for k, v in sorted(skipped.items()))
        warnings.append(f"{path}: ignored records: {listed}")
    chosen = next((k for k in _LASER_PREFERENCE if k in lasers), None)
    for other in lasers:
        if other != chosen:
            warnings.append(f"{path}: ignored {len(lasers[other].t)} {other} scans (only {chosen} is used)")

    lidar, scans = None, None
    if chosen is not None:
        lidar, scans = _laser_stream(path, chosen, lasers[chosen], params, no_return_m, warnings)

    odometry = recorded = None
    if odom_t:
        order = time_order(np.array(odom_t), path, "ODOM", warnings, _line_label(odom_lines))
        recorded = OdometryStream(t_s=np.array(odom_t)[order], poses=np.frombuffer(odom_poses).reshape(-1, 3)[order])
        repaired = _backing_up_forward(recorded, np.array(odom_tv)[order], path, warnings)
        odometry = recorded if repaired is None else repaired
    if chosen is not None and _carries_odometry(lasers[chosen]):
        laser = lasers[chosen]
        order = time_order(np.array(laser.t), path, chosen, [], _line_label(laser.lines))
        own = OdometryStream(t_s=np.array(laser.t)[order], poses=laser.robot_poses()[order])
        if odometry is None or recorded is None:
            odometry = own
            warnings.append(f"{path}: no ODOM records; odometry taken from the {chosen} robot poses")
        else:
            if odometry is not recorded:  # the records' own poses carried along with the repair
                own = _through(own, recorded, odometry)
            odometry = _with_scans_own_poses(odometry, own, chosen, path, warnings)
    elif odometry is None:
        warnings.append(f"{path}: no odometry (no ODOM records and no robot poses in the laser records)")
    if odometry is None and scans is None:
        raise LogFormatError("no ODOM and no laser records: not a usable CARMEN log", path=str(path))
    return DriveLog(vehicle=VehicleModel(kind=MotionModelKind.ODOMETRY, name="carmen robot"),
                    lidar=lidar, scans=scans, odometry=odometry, source_format="carmen",
                    source_path=str(path), warnings=warnings)


def _carries_odometry(laser: _Laser) -> bool:
    """Whether the laser records carry the robot's odometry pose (FLASER, ROBOTLASER: not all the same)."""
    poses = laser.robot_poses()
    if len(poses) < 2:
        return False
    return bool(np.any(poses != poses[0]))


def _backing_up_forward(odom: OdometryStream, tv_m_s: np.ndarray, path: Path,
                        warnings: list[str]) -> OdometryStream | None:
    """The ODOM stream with its increments turned back where the records say the robot backs up
    (``tv`` below -0.02 m/s) but their poses advance forward (more than 1 mm along the heading): an
    odometry integrated with the speed's magnitude. None where no record does that."""
    steps = relative(odom.poses[:-1], odom.poses[1:])
    wrong = (tv_m_s[1:] < -0.02) & (steps[:, 0] > 1e-3)
    if not wrong.any():
        return None
    warnings.append(f"{path}: at {int(wrong.sum())} ODOM records the robot backs up (tv < 0) while the pose "
                    "advances forward: those steps are taken backwards")
    steps[wrong, :2] *= -1.0
    poses = np.empty_like(odom.poses)
    poses[0] = odom.poses[0]
    for i, step in enumerate(steps, start=1):
        poses[i] = compose(poses[i - 1], step)
    return OdometryStream(t_s=odom.t_s, poses=poses)


def _through(own: OdometryStream, before: OdometryStream, after: OdometryStream) -> OdometryStream:
    """``own`` poses (laser records' odometry) carried from the ``before`` odometry frame to the
    ``after`` one: each keeps its offset from ``before`` at its stamp."""
    at_before = interpolate(before.t_s, before.poses, own.t_s)
    at_after = interpolate(after.t_s, after.poses, own.t_s)
    return OdometryStream(t_s=own.t_s, poses=compose(at_after, relative(at_before, own.poses)))


def _with_scans_own_poses(odom: OdometryStream, own: OdometryStream, kind: str, path: Path,
                          warnings: list[str]) -> OdometryStream:
    """The ODOM stream ``odom`` with each laser record's own odometry pose (``own``, at the records'
    stamps) put in wherever the ODOM records interpolated at that stamp differ from it by more than
    1 mm or 1 mrad (an ODOM record at the same stamp gives way). Logs whose records agree keep their
    ODOM stream as it is; a warning counts the scans more than 0.05 m or 0.05 rad off."""
    at = interpolate(odom.t_s, odom.poses, own.t_s)
    off_m = np.hypot(at[:, 0] - own.poses[:, 0], at[:, 1] - own.poses[:, 1])
    off_rad = np.abs(wrap_angle(at[:, 2] - own.poses[:, 2]))
    differ = (off_m > 1e-3) | (off_rad > 1e-3)
    if not differ.any():
        return odom
    far = int(np.count_nonzero((off_m > 0.05) | (off_rad > 0.05)))
    if far:
        warnings.append(f"{path}: at {far} of {len(own)} {kind} records the ODOM records at the record's "
                        f"timestamp put the robot more than 0.05 m or 0.05 rad (up to {off_m.max():.2f} m, "
                        f"{off_rad.max():.2f} rad) from the odometry pose the record carries (late or jittered "
                        "timestamps): each scan is paired with its own record's pose")
    kept = ~np.isin(odom.t_s, own.t_s[differ])
    t_s = np.concatenate([odom.t_s[kept], own.t_s[differ]])
    poses = np.concatenate([odom.poses[kept], own.poses[differ]])
    order = np.argsort(t_s, kind="stable")
    return OdometryStream(t_s=t_s[order], poses=poses[order])


def _line_label(lines: Sequence[int]):
    return lambda i: f"line {lines[i]}"


def _laser_stream(path: Path, kind: str, laser: _Laser, params: dict[str, str], no_return_m: float | None,
                  warnings: list[str]) -> tuple[LidarModel, ScanStream]:
    counts = np.array(laser.counts, dtype=np.int64)
    n = int(counts.max())
    if counts.min() == 0:
        bad = int(np.argmin(counts))
        raise LogFormatError(f"{kind} scan has no beams", path=str(path), location=f"line {laser.lines[bad]}")
    side = "rear" if kind in ("RLASER", "ROBOTLASER2") else "front"
    if laser.geometry is not None:
        angle_min, increment, max_range = laser.geometry
        threshold = max_range if max_range and max_range > 0 else DEFAULT_NO_RETURN_M
    else:
        angle_min = -np.pi / 2
        increment = laser.increments[0]
        threshold = DEFAULT_NO_RETURN_M
    if f"robot_{side}_laser_max" in params:
        threshold = _param_float(params, f"robot_{side}_laser_max", path)
    if no_return_m is not None:
        threshold = no_return_m
    raw = _padded(np.frombuffer(laser.ranges, dtype=np.float64), counts, n)
    label = _line_label(laser.lines)
    saturation = _saturation_value(raw, threshold)
    if saturation is not None:
        warnings.append(f"{path}: {kind}: range {saturation:g} m fills many beams; treated as no return")
        threshold = saturation
    ranges = clean_ranges(raw, path, kind, no_return_at_or_above_m=threshold, location_of=label)
    order = time_order(np.array(laser.t), path, kind, warnings, label)
    lidar = LidarModel(num_beams=n, angle_min_rad=float(angle_min), angle_increment_rad=float(increment),
                       range_min_m=0.0, range_max_m=float(threshold),
                       T_vehicle_from_lidar=_mounting(path, side, laser, params), name=f"carmen {kind}")
    offsets = np.array(laser.starts) - angle_min if laser.starts else np.zeros(len(laser.t))
    changing = bool(np.any(offsets != 0.0))
    if changing or (counts != n).any():
        warnings.append(f"{path}: {kind}: beam geometry changes from scan to scan ({len(np.unique(offsets))} "
                        f"start angles, {counts.min()}-{n} beams); carried per scan")
    return lidar, ScanStream(t_s=np.array(laser.t)[order], ranges_m=ranges[order],
                             angle_offset_rad=offsets[order] if changing else None)


def _padded(ranges: np.ndarray, counts: np.ndarray, n: int) -> np.ndarray:
    """(N, n) ranges from every scan's ranges one after the other (``counts`` each): scans with fewer
    beams padded with ``inf`` (no return) at their end."""
    if (counts == n).all():
        return ranges.reshape(len(counts), n).copy()
    out = np.full((len(counts), n), np.inf)
    out[np.arange(n) < counts[:, None]] = ranges  # row after row, as the ranges were read
    return out


def _saturation_value(raw: np.ndarray, threshold: float) -> float | None:
    """A range below ``threshold`` that fills a large share of beams: the scanner's no-return code."""
    below = raw[(raw >= SATURATION_MIN_M) & (raw < threshold)]
    if below.size == 0:
        return None
    top = below.max()
    if np.count_nonzero(below == top) >= SATURATION_SHARE * raw.size:
        return float(top)
    return None


def _param_float(params: dict[str, str], name: str, path: Path) -> float:
    try:
        return float(params[name])
    except ValueError:
        raise LogFormatError(f"PARAM {name} is not a number: {params[name]!r}", path=str(path)) from None


def _mounting(path: Path, side: str, laser: _Laser, params: dict[str, str]) -> np.ndarray:
    """T_vehicle_from_lidar from PARAM offsets, else from the first record's laser vs robot pose."""
    names = [f"robot_{side}laser_offset", f"robot_{side}laser_side_offset", f"robot_{side}laser_angular_offset"]
    if any(name in params for name in names):
        x, y, yaw = (_param_float(params, name, path) if name in params else 0.0 for name in names)
        if side == "rear" and names[2] not in params:
            yaw = np.pi
        return to_matrix_4x4(np.array([x, y, yaw]))
    if laser.laser_pose:
        return to_matrix_4x4(relative(np.array(laser.robot_pose[0:3]), np.array(laser.laser_pose[0:3])))
    return to_matrix_4x4(np.array([0.0, 0.0, np.pi if side == "rear" else 0.0]))


# ---------------------------------------------------------------------------------------------- writing

def _flaser_geometry(lidar: LidarModel) -> bool:
    """Whether the LiDAR's beams follow the FLASER convention (180 deg from -90 deg)."""
    n = lidar.num_beams
    increment = np.pi / (n - 1) if n % 2 == 1 and n > 1 else np.pi / n
    return abs(lidar.angle_min_rad + np.pi / 2) < 1e-6 and abs(lidar.angle_increment_rad - increment) < 1e-9


def write(log: DriveLog, out_dir: Path, name: str = "log") -> Path:
    """Write ``out_dir/<name>.clf``: PARAM lines, ODOM lines at the odometry stamps (dead-reckoned
    from the encoders when the log has no odometry), and one FLASER (or ROBOTLASER1 when the beams
    do not follow the FLASER convention or their start angle changes from scan to scan) per scan.
    Ranges in mm precision, poses in micrometres."""
    odometry = odometry_poses(log)
    path = Path(out_dir) / f"{name}.clf"
    lines = [f"# written by lidarmap from a {log.source_format} log",
             "# ODOM x y theta tv rv accel ts host logger_ts; FLASER/ROBOTLASER1 see CARMEN docs"]
    if log.scans is not None and log.lidar is not None:
        lidar = log.lidar
        if not is_planar_4x4(lidar.T_vehicle_from_lidar):
            raise LogFormatError("CARMEN cannot store a tilted LiDAR (its mounting has roll or pitch)",
                                 path=str(path))
        mount = planar_from_4x4(lidar.T_vehicle_from_lidar)
        lines.append(f"PARAM robot_frontlaser_offset {mount[0]:.6f} lidarmap 0")
        lines.append(f"PARAM robot_frontlaser_side_offset {mount[1]:.6f} lidarmap 0")
        lines.append(f"PARAM robot_frontlaser_angular_offset {mount[2]:.9f} lidarmap 0")
        lines.append(f"PARAM robot_front_laser_max {lidar.range_max_m:.6f} lidarmap 0")
    records: list[tuple[float, int, str]] = []
    for t, (x, y, th) in zip(odometry.t_s, odometry.poses, strict=True):
        records.append((float(t), 0, f"ODOM {x:.6f} {y:.6f} {th:.6f} 0 0 0 {t:.6f} lidarmap {t:.6f}"))
    if log.scans is not None and log.lidar is not None:
        records.extend(_laser_lines(log.lidar, log.scans, odometry, mount))
    records.sort(key=lambda r: (r[0], r[1]))
    lines.extend(r[2] for r in records)
    path.write_text("\n".join(lines) + "\n")
    return path


def _laser_lines(lidar: LidarModel, scans: ScanStream, odometry: OdometryStream,
                 mount: np.ndarray) -> list[tuple[float, int, str]]:
    robot = interpolate(odometry.t_s, odometry.poses, scans.t_s)
    laser = compose(robot, mount)
    no_return = max(lidar.range_max_m, DEFAULT_NO_RETURN_M) + 1.91
    flaser = _flaser_geometry(lidar) and scans.angle_offset_rad is None
    offsets = np.zeros(len(scans)) if scans.angle_offset_rad is None else scans.angle_offset_rad
    out = []
    for k in range(len(scans)):
        t = float(scans.t_s[k])
        r = np.where(np.isfinite(scans.ranges_m[k]), scans.ranges_m[k], no_return)
        ranges = " ".join(f"{v:.3f}" for v in r)
        poses = " ".join(f"{v:.6f}" for v in (*laser[k], *robot[k]))
        if flaser:
            line = f"FLASER {lidar.num_beams} {ranges} {poses} {t:.6f} lidarmap {t:.6f}"
        else:
            fov = lidar.num_beams * lidar.angle_increment_rad
            start = lidar.angle_min_rad + float(offsets[k])
            line = (f"ROBOTLASER1 0 {start:.9f} {fov:.9f} {lidar.angle_increment_rad:.12f} "
                    f"{no_return:.3f} 0.01 0 {lidar.num_beams} {ranges} 0 {poses} 0 0 0 0 0 "
                    f"{t:.6f} lidarmap {t:.6f}")
        out.append((t, 1, line))
    return out
