"""The UCSD ECE276A car logs (KAIST-style urban drive): a folder with ``sensor_data/``, ``param/`` and
optionally ``stereo_images/``.

- ``sensor_data/encoder.csv``: ``ns, left, right`` cumulative wheel ticks (no header).
- ``sensor_data/fog.csv``: ``ns, delta roll, delta pitch, delta yaw`` [rad] since the previous row;
  loaded as yaw rate = delta yaw / dt.
- ``sensor_data/lidar.csv``: ``ns, r_0 .. r_285`` [m], SICK LMS511, beams from -5 deg to 185 deg
  (evenly spaced over the stated start and end angles), 0 = no return, 80 m maximum.
- ``stereo_images/stereo_left|stereo_right/<ns>.png``: left and right images named by stamp.
- ``param/EncoderParameter.txt`` (resolution, left/right wheel diameter, wheel base),
  ``Vehicle2Lidar.txt`` / ``Vehicle2FOG.txt`` / ``Vehicle2Stereo.txt`` (``RPY:`` deg, ``R:`` 9 values
  row-major, ``T:`` m; vehicle <- sensor), ``lidar_param.txt``, and the stereo calibration
  (``left_camera.yaml``, ``right_camera.yaml``, ``stereo_param.txt``; read by
  ``slam_engine.texture.calibration.load_ece276a_stereo_calibration``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import clean_ranges, time_order
from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    LidarModel,
    MotionModelKind,
    ScanStream,
    StereoStream,
    VehicleModel,
)

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def sniff(path: Path) -> bool:
    """A folder with ``sensor_data/encoder.csv`` whose first row is three comma-separated numbers."""
    encoder = Path(path) / "sensor_data" / "encoder.csv"
    if not encoder.is_file():
        return False
    try:
        with open(encoder, encoding="utf-8", errors="replace") as handle:
            first = handle.readline(256).strip().split(",")  # bounded: a row is three numbers
    except OSError:
        return False
    return len(first) == 3 and all(re.fullmatch(_NUMBER, tok.strip()) for tok in first)


# ---------------------------------------------------------------------------------------------- params

def _param_text(param_dir: Path, name: str) -> str:
    path = param_dir / name
    if not path.is_file():
        raise LogFormatError("missing calibration file", path=str(path))
    return path.read_text(encoding="utf-8", errors="replace")


def _labelled_numbers(text: str, label: str, count: int, path: Path) -> np.ndarray:
    """The ``count`` numbers after ``label:`` on its line."""
    match = re.search(rf"^\s*{re.escape(label)}\s*:(.*)$", text, flags=re.MULTILINE | re.IGNORECASE)
    if not match:
        raise LogFormatError(f"no '{label}:' line", path=str(path))
    values = re.findall(_NUMBER, match.group(1))
    if len(values) < count:
        raise LogFormatError(f"'{label}:' needs {count} numbers, found {len(values)}", path=str(path),
                             location=label)
    return np.array(values[:count], dtype=np.float64)


def read_extrinsic(param_dir: Path, name: str) -> np.ndarray:
    """4x4 T_vehicle_from_sensor from a ``Vehicle2*.txt`` file (its ``R:`` and ``T:`` lines)."""
    text = _param_text(param_dir, name)
    path = param_dir / name
    R = _labelled_numbers(text, "R", 9, path).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise LogFormatError("R is not a rotation matrix", path=str(path), location="R")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = _labelled_numbers(text, "T", 3, path)
    return T


def read_vehicle(param_dir: Path) -> VehicleModel:
    """Differential-drive model from ``EncoderParameter.txt`` (+ the FOG's placement when present)."""
    text = _param_text(param_dir, "EncoderParameter.txt")
    path = param_dir / "EncoderParameter.txt"
    resolution = _labelled_numbers(text, "Encoder resolution", 1, path)[0]
    left = _labelled_numbers(text, "Encoder left wheel diameter", 1, path)[0]
    right = _labelled_numbers(text, "Encoder right wheel diameter", 1, path)[0]
    base = _labelled_numbers(text, "Encoder wheel base", 1, path)[0]
    if min(resolution, left, right, base) <= 0:
        raise LogFormatError("encoder parameters must be positive", path=str(path))
    fog = read_extrinsic(param_dir, "Vehicle2FOG.txt") if (param_dir / "Vehicle2FOG.txt").is_file() else np.eye(4)
    return VehicleModel(kind=MotionModelKind.DIFFERENTIAL, ticks_per_revolution=float(resolution),
                        wheel_diameters_m=(float(left), float(right)), wheel_names=("left", "right"),
                        track_width_m=float(base), T_vehicle_from_gyro=fog, name="ECE276A car")


def read_lidar(param_dir: Path, num_beams: int) -> LidarModel:
    """LMS511 geometry from ``lidar_param.txt`` and the mounting from ``Vehicle2Lidar.txt``."""
    text = _param_text(param_dir, "lidar_param.txt")
    path = param_dir / "lidar_param.txt"
    start = _labelled_numbers(text, "Start angle", 1, path)[0]
    end = _labelled_numbers(text, "End angle", 1, path)[0]
    resolution = _labelled_numbers(text, "Angular resolution", 1, path)[0]
    max_range = _labelled_numbers(text, "Max range", 1, path)[0]
    increment = (end - start) / max(num_beams - 1, 1)
    if abs(increment - resolution) > 0.01 * resolution:
        raise LogFormatError(f"{num_beams} beams from {start} to {end} deg are {increment:.4f} deg apart, "
                             f"but the stated resolution is {resolution} deg", path=str(path))
    return LidarModel(num_beams=num_beams, angle_min_rad=float(np.radians(start)),
                      angle_increment_rad=float(np.radians(increment)), range_min_m=0.0,
                      range_max_m=float(max_range), T_vehicle_from_lidar=read_extrinsic(param_dir, "Vehicle2Lidar.txt"),
                      name="SICK LMS511")


# ---------------------------------------------------------------------------------------------- csv

def _read_csv(path: Path, columns: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(stamps int64 ns, values float64 (N, columns-1)) of a headerless CSV; errors name the line."""
    if not path.is_file():
        raise LogFormatError("missing file", path=str(path))
    stamps: list[int] = []
    rows: list[list[str]] = []
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line_no, line in enumerate(handle, start=1):
            line = line.strip()
            if not line:
                continue
            fields = line.split(",")
            if columns is None:
                columns = len(fields)
            if len(fields) != columns:
                raise LogFormatError(f"row has {len(fields)} fields, expected {columns} (truncated?)",
                                     path=str(path), location=f"line {line_no}")
            try:
                stamp = int(fields[0])
            except ValueError:
                raise LogFormatError(f"timestamp {fields[0]!r} is not an integer nanosecond count",
                                     path=str(path), location=f"line {line_no}") from None
            if not 0 <= stamp < 2**63:
                raise LogFormatError(f"timestamp {fields[0]!r} is outside 0..2^63 ns", path=str(path),
                                     location=f"line {line_no}")
            stamps.append(stamp)
            rows.append(fields[1:])
    if not rows:
        raise LogFormatError("file holds no rows", path=str(path))
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError as error:
        bad = next(i for i, r in enumerate(rows) if not all(re.fullmatch(_NUMBER + "|nan|inf", f.strip(), re.I)
                                                          for f in r))
        raise LogFormatError(f"not a number: {error}", path=str(path), location=f"row {bad + 1}") from None
    return np.array(stamps, dtype=np.int64), values


def load(path: Path) -> DriveLog:
    """Read a car log folder; ``param/`` must hold the calibration of every sensor present."""
    folder = Path(path)
    data, param = folder / "sensor_data", folder / "param"
    if not param.is_dir():
        raise LogFormatError("missing calibration folder param/", path=str(folder))
    warnings: list[str] = []
    vehicle = read_vehicle(param)

    ns, ticks = _read_csv(data / "encoder.csv", 3)
    t = ns * 1e-9
    if not (np.isfinite(ticks).all() and np.all(ticks == np.round(ticks)) and np.all(np.abs(ticks) < 2**62)):
        raise LogFormatError("encoder counts must be (finite) integers", path=str(data / "encoder.csv"))
    order = time_order(t, data / "encoder.csv", "encoder", warnings, lambda i: f"line {i + 1}")
    encoders = EncoderStream(t_s=t[order], ticks=ticks[order].astype(np.int64))

    gyro = None
    if (data / "fog.csv").is_file():
        ns, deltas = _read_csv(data / "fog.csv", 4)
        t = ns * 1e-9
        order = time_order(t, data / "fog.csv", "fog", warnings, lambda i: f"line {i + 1}")
        t, delta_yaw = t[order], deltas[order, 2]
        if not np.all(np.isfinite(delta_yaw)):
            raise LogFormatError("delta yaw is not finite", path=str(data / "fog.csv"),
                                 location=f"line {int(np.flatnonzero(~np.isfinite(delta_yaw))[0]) + 1}")
        if t.size < 2:
            raise LogFormatError("needs at least two rows to turn yaw deltas into rates", path=str(data / "fog.csv"))
        dt = np.diff(t, prepend=t[0] - (t[1] - t[0]))
        gyro = GyroStream(t_s=t, yaw_rate_rad_s=delta_yaw / dt)
    else:
        warnings.append(f"{folder}: no sensor_data/fog.csv; heading from wheels only")

    lidar, scans = None, None
    if (data / "lidar.csv").is_file():
        ns, ranges = _read_csv(data / "lidar.csv", None)
        lidar = read_lidar(param, ranges.shape[1])
        t = ns * 1e-9
        label = lambda i: f"line {i + 1}"  # noqa: E731
        clean = clean_ranges(ranges, data / "lidar.csv", "lidar", no_return_at_or_above_m=None, location_of=label)
        clean[clean > lidar.range_max_m] = np.inf
        order = time_order(t, data / "lidar.csv", "lidar", warnings, label)
        scans = ScanStream(t_s=t[order], ranges_m=clean[order])
    else:
        warnings.append(f"{folder}: no sensor_data/lidar.csv; the log has no scans (dead reckoning only)")

    stereo = _stereo(folder, param, warnings)
    return DriveLog(vehicle=vehicle, lidar=lidar, scans=scans, encoders=encoders, gyro=gyro, stereo=stereo,
                    source_format="ece276a-car", source_path=str(folder), warnings=warnings)


def _stereo(folder: Path, param: Path, warnings: list[str]) -> StereoStream | None:
    left_dir, right_dir = folder / "stereo_images" / "stereo_left", folder / "stereo_images" / "stereo_right"
    if not left_dir.is_dir():
        return None
    if not right_dir.is_dir():
        raise LogFormatError("stereo_images/stereo_left exists but stereo_right does not", path=str(folder))
    left = {p.stem: p for p in left_dir.glob("*.png") if p.stem.isdigit()}
    right = {p.stem: p for p in right_dir.glob("*.png") if p.stem.isdigit()}
    common = sorted(set(left) & set(right), key=int)
    if len(common) < len(left) or len(common) < len(right):
        warnings.append(f"{folder}: {len(left) - len(common)} left and {len(right) - len(common)} right images "
                        "have no partner with the same stamp; skipped")
    if not common:
        return None
    try:
        from slam_engine.texture.calibration import load_ece276a_stereo_calibration
    except ImportError:
        warnings.append(f"{folder}: stereo calibration reader not available in this build; stereo skipped")
        return None
    calibration = load_ece276a_stereo_calibration(param)
    return StereoStream(t_s=np.array([int(s) for s in common], dtype=np.int64) * 1e-9,
                        left_images=[str(left[s]) for s in common], right_images=[str(right[s]) for s in common],
                        calibration=calibration)


# ---------------------------------------------------------------------------------------------- writing

def rpy_deg(R: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw [deg] with R = Rz(yaw) Ry(pitch) Rx(roll) (XYZ extrinsic)."""
    pitch = np.arcsin(-np.clip(R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return float(np.degrees(roll)), float(np.degrees(pitch)), float(np.degrees(yaw))


def _extrinsic_text(title: str, T: np.ndarray, note: str = "") -> str:
    R = T[:3, :3]
    lines = [title, "RPY(roll/pitch/yaw = XYZ extrinsic, degree), R(rotation matrix), T(translation matrix, meter)",
             "RPY: " + " ".join(f"{v:.6g}" for v in rpy_deg(R)),
             "R: " + " ".join(f"{v:.9g}" for v in R.ravel()) + " ",
             "T: " + " ".join(f"{v:.9g}" for v in T[:3, 3])]
    return "\n".join(lines) + ("\n\n" + note if note else "") + "\n"


def write(log: DriveLog, out_dir: Path) -> Path:
    """Write ``out_dir/sensor_data/*.csv`` and ``out_dir/param/*.txt``; returns ``out_dir``.

    A stereo stream is written as ``stereo_images/stereo_left|stereo_right/<ns>.png`` (frames as
    they are: raw Bayer stays single-channel) with ``param/left_camera.yaml``, ``right_camera.yaml``,
    ``stereo_param.txt`` and ``Vehicle2Stereo.txt``.
    """
    out_dir = Path(out_dir)
    vehicle = log.vehicle
    if vehicle.kind != MotionModelKind.DIFFERENTIAL or log.encoders is None or log.encoders.ticks.shape[1] != 2:
        raise LogFormatError("ECE276A car logs hold a differential vehicle's two wheel encoders", path=str(out_dir))
    if vehicle.ticks_per_revolution is None or vehicle.wheel_diameters_m is None or vehicle.track_width_m is None:
        raise LogFormatError("the vehicle model lacks ticks per revolution, wheel diameters or track width",
                             path=str(out_dir))
    data, param = out_dir / "sensor_data", out_dir / "param"
    data.mkdir(parents=True, exist_ok=True)
    param.mkdir(parents=True, exist_ok=True)
    left_d, right_d = (vehicle.wheel_diameters_m * 2)[:2]
    (param / "EncoderParameter.txt").write_text(
        "Encoder calibrated parameter\n"
        f"Encoder resolution: {vehicle.ticks_per_revolution:g}\n"
        f"Encoder left wheel diameter: {left_d:.9g}\n"
        f"Encoder right wheel diameter: {right_d:.9g}\n"
        f"Encoder wheel base: {vehicle.track_width_m:.9g}\n\n"
        "* The encoder data is stored as [timestamp, left count, right count].\n")
    _write_rows(data / "encoder.csv", log.encoders.t_s, log.encoders.ticks, "%d")
    if log.gyro is not None:
        (param / "Vehicle2FOG.txt").write_text(_extrinsic_text(
            "FOG (Fiber Optic Gyro) extrinsic calibration parameter from vehicle", vehicle.T_vehicle_from_gyro,
            "* The sensor measurements are stored as [timestamp, delta roll, delta pitch, delta yaw] in radians."))
        t = np.asarray(log.gyro.t_s, dtype=np.float64)
        if t.size < 2:
            raise LogFormatError("FOG needs at least two samples", path=str(data / "fog.csv"))
        dt = np.diff(t, prepend=t[0] - (t[1] - t[0]))
        deltas = np.zeros((t.size, 3))
        deltas[:, 2] = log.gyro.yaw_rate_rad_s * dt
        _write_rows(data / "fog.csv", t, deltas, "%.12e")
    if log.scans is not None and log.lidar is not None:
        lidar = log.lidar
        start = np.degrees(lidar.angle_min_rad)
        increment = np.degrees(lidar.angle_increment_rad)
        end = start + increment * (lidar.num_beams - 1)
        (param / "lidar_param.txt").write_text(
            f"FOV: {end - start:.6g} (degree)\nStart angle: {start:.6g} (degree)\nEnd angle: {end:.6g} (degree)\n"
            f"Angular resolution: {increment:.6g} (degree)\nMax range: {lidar.range_max_m:.6g} (meter)\n\n"
            "* LiDAR rays with value 0.0 represent infinite range observations.\n")
        (param / "Vehicle2Lidar.txt").write_text(_extrinsic_text(
            f"Lidar sensor ({lidar.name}) extrinsic calibration parameter from vehicle", lidar.T_vehicle_from_lidar))
        ranges = np.where(np.isfinite(log.scans.ranges_m), log.scans.ranges_m, 0.0)
        _write_rows(data / "lidar.csv", log.scans.t_s, ranges, "%.3f")
    if log.stereo is not None:
        _write_stereo(log.stereo, out_dir)
    return out_dir


def _write_stereo(stereo: StereoStream, out_dir: Path) -> None:
    """Stereo frames named by their nanosecond stamps, and the pair's calibration files."""
    import cv2

    from slam_engine.texture.calibration import write_camera_yaml
    from slam_engine.texture.images import read_frame

    cal, param = stereo.calibration, out_dir / "param"
    write_camera_yaml(param / "left_camera.yaml", cal.image_size_wh, cal.K_left, cal.D_left, cal.R_left, cal.P_left,
                      "/stereo/left")
    write_camera_yaml(param / "right_camera.yaml", cal.image_size_wh, cal.K_right, cal.D_right, cal.R_right,
                      cal.P_right, "/stereo/right")
    (param / "stereo_param.txt").write_text(f"Baseline of stereo cameras: {cal.baseline_m * 1000.0:.12g} (mm)\n")
    (param / "Vehicle2Stereo.txt").write_text(_extrinsic_text(
        "Stereo camera (based on left camera) extrinsic calibration parameter from vehicle",
        cal.T_vehicle_from_camera))
    ns = np.round(np.asarray(stereo.t_s, dtype=np.float64) * 1e9).astype(np.int64)
    if np.unique(ns).size != ns.size:
        raise LogFormatError("two stereo frames share one nanosecond stamp", path=str(out_dir / "stereo_images"))
    for side, frames in (("stereo_left", stereo.left_images), ("stereo_right", stereo.right_images)):
        folder = out_dir / "stereo_images" / side
        folder.mkdir(parents=True, exist_ok=True)
        for k, (stamp, frame) in enumerate(zip(ns.tolist(), frames, strict=True)):
            image = read_frame(frame, f"{side} frame {k}")
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(folder / f"{stamp}.png"), image)


def _write_rows(path: Path, t_s: np.ndarray, values: np.ndarray, fmt: str) -> None:
    """Headerless CSV rows ``ns,v1,v2,...`` (stamps rounded to integer nanoseconds)."""
    ns = np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)
    row_fmt = ",".join([fmt] * values.shape[1])
    with open(path, "w") as out:
        rows = zip(ns.tolist(), values.tolist(), strict=True)
        out.writelines(f"{stamp}," + row_fmt % tuple(row) + "\n" for stamp, row in rows)
