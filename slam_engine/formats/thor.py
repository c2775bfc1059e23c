"""The THOR skid-steer robot's logs: UPenn ESE650 (.mat) and UCSD ECE276A (.npz).

A log is one *set* NN in one folder: ``EncodersNN`` (required), ``imuNN``/``ImuNN``, ``HokuyoNN``,
``KinectNN`` (.npz timestamps) and, when present, ``dataRGBD/DisparityNN/disparityNN_k.png`` and
``dataRGBD/RGBNN/rgbNN_k.png`` (k from 1) beside or above the set's folder. Pass the folder (when it
holds one set) or any file of the set.

Layouts (as the course loaders read them):

- Encoders.mat: struct ``Encoders`` with ``counts`` int16 (4, N) and ``ts`` (1, N);
  Encoders.npz: ``counts`` (4, N), ``time_stamps`` (N,). Rows FR, FL, RR, RL; per-sample tick
  *deltas* (the counter resets on each read), 360 ticks per revolution, 254 mm wheels.
- imu.mat: ``vals`` (6, N) = acc x y z [g], gyro x y z [rad/s], ``ts`` (1, N);
  Imu.npz: ``angular_velocity`` (3, N) [rad/s], ``linear_acceleration`` (3, N) [g], ``time_stamps``.
- Hokuyo.mat: struct ``Hokuyo0`` with ``angles`` (1081, 1) [rad], ``ranges`` (1081, N) [m], ``ts``
  (1, N); Hokuyo.npz: ``angle_min``, ``angle_max``, ``angle_increment``, ``range_min``,
  ``range_max``, ``ranges`` (1081, N), ``time_stamps``. UTM-30LX: -135..135 deg, 0.25 deg, 30 m.
- Kinect.npz: ``disparity_time_stamps``, ``rgb_time_stamps``.

Vehicle frame: origin at the body centre (the skid-steer's turning centre), 165 mm ahead of the
rear axle; the LiDAR sits 133.23 mm ahead of it and 514.35 mm up.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import clean_ranges, time_order
from slam_engine.frontend.odometry import integrate_yaw_rate, side_distances_m
from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    LidarModel,
    MotionModelKind,
    RgbdStream,
    ScanStream,
    VehicleModel,
)
from slam_engine.texture.calibration import thor_kinect_calibration

# Effective track width [m] (skid included). Fitting the wheel-distance difference to the ECE276A .npz
# IMU yaw gives 0.75 m on sets 20 and 21, and wheel-only dead reckoning with 0.75 m brings all five
# ESE650 sets (20-24, which return to their start) back within 1-4 m of it (0.93 m: 8-23 m). The
# wheels themselves are about 0.47 m apart. See tests/test_formats_thor.py.
EFFECTIVE_TRACK_M = 0.75
# The ESE650 .mat imu yaw rates are about 1/1.21 of the ECE276A .npz ones at the same stamps (sets 20,
# 21: least-squares ratio 1.207 and 1.227), and fitting them gives an inconsistent 0.91-0.96 m track.
MAT_GYRO_UNDER_READ = 1.21
THOR_VEHICLE = VehicleModel(kind=MotionModelKind.SKID_STEER, ticks_per_revolution=360,
                            wheel_diameters_m=(0.254, 0.254, 0.254, 0.254),
                            wheel_names=("front_right", "front_left", "rear_right", "rear_left"),
                            track_width_m=EFFECTIVE_TRACK_M, gyro_lowpass_hz=10.0, name="THOR")
T_VEHICLE_FROM_LIDAR = np.array([[1.0, 0, 0, 0.13323], [0, 1.0, 0, 0], [0, 0, 1.0, 0.51435], [0, 0, 0, 1.0]])
UTM_30LX = LidarModel(num_beams=1081, angle_min_rad=float(np.radians(-135.0)),
                      angle_increment_rad=float(np.radians(0.25)), range_min_m=0.1, range_max_m=30.0,
                      T_vehicle_from_lidar=T_VEHICLE_FROM_LIDAR, name="Hokuyo UTM-30LX")
_SET_FILE = re.compile(r"^(encoders|imu|hokuyo|kinect)(\d+)\.(mat|npz)$", re.IGNORECASE)


def _set_files(folder: Path) -> dict[int, dict[str, Path]]:
    """{set number: {"encoders"|"imu"|"hokuyo"|"kinect": path}} of the set files in ``folder``."""
    sets: dict[int, dict[str, Path]] = {}
    if not folder.is_dir():
        return sets
    for child in folder.iterdir():
        match = _SET_FILE.match(child.name)
        if match and child.is_file():
            sets.setdefault(int(match.group(2)), {})[match.group(1).lower()] = child
    return sets


def _looks_like_encoders(path: Path) -> bool:
    try:
        if path.suffix.lower() == ".npz":
            with zipfile.ZipFile(path) as archive:
                return "counts.npy" in archive.namelist()
        from scipy.io import whosmat

        return any(name == "Encoders" for name, _, _ in whosmat(str(path)))
    except Exception:  # scipy/zipfile raise many kinds of errors on a damaged file: not a THOR file then
        return False


def sniff(path: Path) -> bool:
    """A THOR set file (its content checked), or a folder holding an EncodersNN file."""
    if path.is_file():
        match = _SET_FILE.match(path.name)
        if not match:
            return False
        encoders = _set_files(path.parent).get(int(match.group(2)), {}).get("encoders")
        return encoders is not None and _looks_like_encoders(encoders)
    return any("encoders" in files and _looks_like_encoders(files["encoders"])
               for files in _set_files(path).values())


def _read(path: Path) -> dict[str, np.ndarray]:
    """Arrays of a .mat (structs flattened to ``struct.field``) or .npz file."""
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as data:
                return {key: np.asarray(data[key]) for key in data.files}
        from scipy.io import loadmat

        raw = loadmat(str(path))
    except Exception as error:  # a damaged .mat/.npz makes scipy/numpy/zipfile raise all sorts of errors
        raise LogFormatError(f"cannot read file ({type(error).__name__}: {error})", path=str(path)) from None
    out: dict[str, np.ndarray] = {}
    for key, value in raw.items():
        if key.startswith("__"):
            continue
        if isinstance(value, np.ndarray) and value.dtype.names:
            for field in value.dtype.names:
                out[f"{key}.{field}"] = np.asarray(value[field][0, 0])
        else:
            out[key] = np.asarray(value)
    return out


def _field(data: dict[str, np.ndarray], names: tuple[str, ...], path: Path) -> np.ndarray:
    for name in names:
        if name in data:
            return data[name]
    raise LogFormatError(f"missing array {' or '.join(names)} (found: {', '.join(sorted(data)) or 'none'})",
                         path=str(path))


def _stamps(data: dict[str, np.ndarray], names: tuple[str, ...], n: int, path: Path) -> np.ndarray:
    t = _field(data, names, path).astype(np.float64).ravel()
    if t.size != n:
        raise LogFormatError(f"{names[0]} has {t.size} stamps but the data has {n} columns", path=str(path),
                             location=names[0])
    return t


def load(path: Path, set_number: int | None = None) -> DriveLog:
    """Read one THOR set: encoders (required), IMU yaw rate, Hokuyo scans, Kinect frames."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    sets = _set_files(folder)
    if set_number is None and path.is_file():
        match = _SET_FILE.match(path.name)
        if not match:
            raise LogFormatError("not a THOR set file (EncodersNN/imuNN/HokuyoNN/KinectNN .mat/.npz)",
                                 path=str(path))
        set_number = int(match.group(2))
    if set_number is None:
        with_encoders = sorted(n for n, files in sets.items() if "encoders" in files)
        if len(with_encoders) != 1:
            listed = ", ".join(map(str, with_encoders)) or "none"
            raise LogFormatError(f"folder must hold exactly one THOR set with an EncodersNN file (sets: {listed}); "
                                 "pass one set's Encoders file", path=str(path))
        set_number = with_encoders[0]
    files = sets.get(set_number, {})
    if "encoders" not in files:
        raise LogFormatError(f"set {set_number} has no Encoders{set_number}.mat/.npz file", path=str(folder))
    warnings: list[str] = []
    encoders = _encoders(files["encoders"], warnings)
    gyro = _imu(files["imu"], warnings) if "imu" in files else None
    if gyro is None:
        warnings.append(f"{folder}: set {set_number} has no IMU file; heading from wheels only")
    lidar, scans = _hokuyo(files["hokuyo"], warnings) if "hokuyo" in files else (UTM_30LX, None)
    if scans is None:
        warnings.append(f"{folder}: set {set_number} has no Hokuyo file; the log has no scans (dead reckoning only)")
    rgbd = _kinect(files["kinect"], folder, set_number, warnings) if "kinect" in files else None
    return DriveLog(vehicle=THOR_VEHICLE, lidar=lidar, scans=scans, encoders=encoders, gyro=gyro, rgbd=rgbd,
                    source_format="thor", source_path=str(files["encoders"]), warnings=warnings)


def _encoders(path: Path, warnings: list[str]) -> EncoderStream:
    data = _read(path)
    counts = _field(data, ("Encoders.counts", "counts"), path)
    if counts.ndim != 2 or counts.shape[0] != 4:
        raise LogFormatError(f"counts must have shape (4, N) (rows FR, FL, RR, RL), got {counts.shape}",
                             path=str(path), location="counts")
    if not np.issubdtype(counts.dtype, np.integer) and not np.all(counts == np.round(counts)):
        raise LogFormatError("counts must be integer tick deltas", path=str(path), location="counts")
    t = _stamps(data, ("Encoders.ts", "time_stamps", "ts"), counts.shape[1], path)
    time_order(t, path, "Encoders", warnings, lambda i: f"Encoders sample {i}")  # validates, warns
    order = np.argsort(t, kind="stable")
    cumulative = np.cumsum(counts.T[order].astype(np.int64), axis=0)
    t_sorted = t[order]
    last_of_stamp = np.append(np.diff(t_sorted) > 0, True)  # repeated stamps: keep the sum of their deltas
    return EncoderStream(t_s=t_sorted[last_of_stamp], ticks=cumulative[last_of_stamp])


def _imu(path: Path, warnings: list[str]) -> GyroStream:
    data = _read(path)
    if "vals" in data:
        if "written_by" not in data:
            warnings.append(f"{path}: ESE650 .mat yaw rates read about {MAT_GYRO_UNDER_READ:.2f}x low against the "
                            "ECE276A .npz copy of the same IMU data and the wheel odometry; prefer the .npz IMU")
        vals = data["vals"]
        if vals.ndim != 2 or vals.shape[0] != 6:
            raise LogFormatError(f"vals must have shape (6, N) (acc xyz [g], gyro xyz [rad/s]), got {vals.shape}",
                                 path=str(path), location="vals")
        yaw_rate = vals[5].astype(np.float64)
    else:
        rates = _field(data, ("angular_velocity",), path)
        if rates.ndim != 2 or rates.shape[0] != 3:
            raise LogFormatError(f"angular_velocity must have shape (3, N), got {rates.shape}", path=str(path),
                                 location="angular_velocity")
        yaw_rate = rates[2].astype(np.float64)
    t = _stamps(data, ("ts", "time_stamps"), yaw_rate.size, path)
    bad = np.flatnonzero(~np.isfinite(yaw_rate))
    if bad.size:
        raise LogFormatError(f"yaw rate is {yaw_rate[bad[0]]}", path=str(path), location=f"IMU sample {bad[0]}")
    order = time_order(t, path, "IMU", warnings, lambda i: f"IMU sample {i}")
    return GyroStream(t_s=t[order], yaw_rate_rad_s=yaw_rate[order])


def _hokuyo(path: Path, warnings: list[str]) -> tuple[LidarModel, ScanStream]:
    data = _read(path)
    ranges = _field(data, ("Hokuyo0.ranges", "ranges"), path).astype(np.float64)
    if ranges.ndim != 2:
        raise LogFormatError(f"ranges must have shape (beams, N), got {ranges.shape}", path=str(path),
                             location="ranges")
    beams = ranges.shape[0]
    if "Hokuyo0.angles" in data:
        angles = data["Hokuyo0.angles"].astype(np.float64).ravel()
        if angles.size != beams:
            raise LogFormatError(f"{angles.size} angles for {beams} beams", path=str(path), location="angles")
        increment = (angles[-1] - angles[0]) / max(beams - 1, 1)
        if np.max(np.abs(np.diff(angles) - increment)) > 1e-6:
            raise LogFormatError("beam angles are not evenly spaced", path=str(path), location="angles")
        angle_min, range_min, range_max = float(angles[0]), UTM_30LX.range_min_m, UTM_30LX.range_max_m
    else:
        angle_min = float(_field(data, ("angle_min",), path))
        increment = float(_field(data, ("angle_increment",), path))
        angle_max = float(_field(data, ("angle_max",), path))
        range_min = float(_field(data, ("range_min",), path))
        range_max = float(_field(data, ("range_max",), path))
        if abs(angle_min + (beams - 1) * increment - angle_max) > 0.5 * abs(increment):
            raise LogFormatError(f"angle_min + (beams-1) * angle_increment != angle_max for {beams} beams",
                                 path=str(path), location="angle_max")
    t = _stamps(data, ("Hokuyo0.ts", "time_stamps", "ts"), ranges.shape[1], path)
    label = lambda i: f"scan {i}"  # noqa: E731
    clean = clean_ranges(ranges.T, path, "ranges", location_of=label)
    clean[(clean < range_min) | (clean > range_max)] = np.inf
    order = time_order(t, path, "Hokuyo", warnings, label)
    lidar = LidarModel(num_beams=beams, angle_min_rad=angle_min, angle_increment_rad=float(increment),
                       range_min_m=range_min, range_max_m=range_max, T_vehicle_from_lidar=T_VEHICLE_FROM_LIDAR,
                       name="Hokuyo UTM-30LX")
    return lidar, ScanStream(t_s=t[order], ranges_m=clean[order])


def _kinect(path: Path, folder: Path, set_number: int, warnings: list[str]) -> RgbdStream | None:
    data = _read(path)
    depth_t = _field(data, ("disparity_time_stamps",), path).astype(np.float64).ravel()
    rgb_t = _field(data, ("rgb_time_stamps",), path).astype(np.float64).ravel()
    for base in (folder, folder.parent):
        disparity_dir = base / "dataRGBD" / f"Disparity{set_number}"
        rgb_dir = base / "dataRGBD" / f"RGB{set_number}"
        if disparity_dir.is_dir():
            break
    else:
        warnings.append(f"{path}: Kinect timestamps but no dataRGBD/Disparity{set_number} images; camera skipped")
        return None
    depth = [str(disparity_dir / f"disparity{set_number}_{k + 1}.png") for k in range(depth_t.size)]
    rgb = [str(rgb_dir / f"rgb{set_number}_{k + 1}.png") for k in range(rgb_t.size)]
    missing = [p for p in depth[:1] + depth[-1:] if not Path(p).is_file()]
    if missing:
        raise LogFormatError(f"disparity image {missing[0]} listed by the timestamps is missing", path=str(path))
    depth_order = time_order(depth_t, path, "disparity", warnings)
    rgb_order = time_order(rgb_t, path, "rgb", warnings)
    return RgbdStream(depth_t_s=depth_t[depth_order], depth_images=[depth[i] for i in depth_order],
                      rgb_t_s=rgb_t[rgb_order], rgb_images=[rgb[i] for i in rgb_order],
                      calibration=thor_kinect_calibration())


# ---------------------------------------------------------------------------------------------- writing

def write(log: DriveLog, out_dir: Path, variant: str = "mat", set_number: int = 20) -> Path:
    """Write set ``set_number`` into ``out_dir`` as .mat (ESE650) or .npz (ECE276A) files; returns
    ``out_dir``. Ticks are written as int16 per-sample deltas; missing ranges as 0. A Kinect stream
    is written as ``KinectNN`` (its timestamps) and ``dataRGBD/DisparityNN/disparityNN_k.png``
    (uint16 raw disparity), ``dataRGBD/RGBNN/rgbNN_k.png``, k from 1."""
    out_dir = Path(out_dir)
    if variant not in ("mat", "npz"):
        raise LogFormatError(f"THOR variant must be 'mat' or 'npz', not {variant!r}")
    if log.vehicle.kind != MotionModelKind.SKID_STEER or log.encoders is None or log.encoders.ticks.shape[1] != 4:
        raise LogFormatError("THOR logs hold a skid-steer robot's four wheel encoders (FR, FL, RR, RL)",
                             path=str(out_dir))
    deltas = np.diff(log.encoders.ticks, axis=0, prepend=log.encoders.ticks[:1])
    if np.abs(deltas).max(initial=0) > np.iinfo(np.int16).max:
        raise LogFormatError("tick deltas exceed int16; sample the encoders faster", path=str(out_dir))
    counts = deltas.T.astype(np.int16)
    t_enc = np.asarray(log.encoders.t_s, dtype=np.float64)
    arrays: dict[str, dict] = {}
    if variant == "mat":
        arrays[f"Encoders{set_number}"] = {"Encoders": {"counts": counts, "ts": t_enc[None, :]}}
    else:
        arrays[f"Encoders{set_number}"] = {"counts": counts, "time_stamps": t_enc}
    if log.gyro is not None:
        n = len(log.gyro)
        rates = np.zeros((3, n))
        rates[2] = log.gyro.yaw_rate_rad_s
        acc = np.tile(np.array([[0.0], [0.0], [1.0]]), (1, n))
        t_imu = np.asarray(log.gyro.t_s, dtype=np.float64)
        if variant == "mat":
            arrays[f"imu{set_number}"] = {"vals": np.vstack([acc, rates]), "ts": t_imu[None, :],
                                          "written_by": "lidarmap"}
        else:
            arrays[f"Imu{set_number}"] = {"angular_velocity": rates, "linear_acceleration": acc,
                                          "time_stamps": t_imu}
    if log.scans is not None and log.lidar is not None:
        lidar = log.lidar
        ranges = np.where(np.isfinite(log.scans.ranges_m), log.scans.ranges_m, 0.0).astype(np.float64).T
        t_scan = np.asarray(log.scans.t_s, dtype=np.float64)
        if variant == "mat":
            arrays[f"Hokuyo{set_number}"] = {"Hokuyo0": {"angles": lidar.beam_angles_rad[:, None], "ranges": ranges,
                                                         "ts": t_scan[None, :]}}
        else:
            arrays[f"Hokuyo{set_number}"] = {
                "angle_min": lidar.angle_min_rad, "angle_increment": lidar.angle_increment_rad,
                "angle_max": float(lidar.beam_angles_rad[-1]), "range_min": lidar.range_min_m,
                "range_max": lidar.range_max_m, "ranges": ranges, "time_stamps": t_scan}
    if log.rgbd is not None:
        arrays[f"Kinect{set_number}"] = _write_kinect_images(log.rgbd, out_dir, set_number)
    for stem, content in arrays.items():
        if variant == "mat":
            from scipy.io import savemat

            savemat(str(out_dir / f"{stem}.mat"), content)
        else:
            np.savez(out_dir / f"{stem}.npz", **content)
    return out_dir


def _write_kinect_images(rgbd: RgbdStream, out_dir: Path, set_number: int) -> dict[str, np.ndarray]:
    """Write the Kinect frames under ``dataRGBD/``; returns the KinectNN file's timestamp arrays."""
    import cv2

    from slam_engine.texture.images import read_frame

    for kind, stamps, frames in (("Disparity", rgbd.depth_t_s, rgbd.depth_images), ("RGB", rgbd.rgb_t_s,
                                                                                     rgbd.rgb_images)):
        folder = out_dir / "dataRGBD" / f"{kind}{set_number}"
        folder.mkdir(parents=True, exist_ok=True)
        if len(frames) != len(stamps):
            raise LogFormatError(f"{len(frames)} {kind} frames for {len(stamps)} timestamps", path=str(folder))
        for k, frame in enumerate(frames):
            image = read_frame(frame, f"{kind} frame {k}")
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(folder / f"{kind.lower()}{set_number}_{k + 1}.png"), image)
    return {"disparity_time_stamps": np.asarray(rgbd.depth_t_s, dtype=np.float64),
            "rgb_time_stamps": np.asarray(rgbd.rgb_t_s, dtype=np.float64)}


def estimate_effective_track_width(log: DriveLog, window_s: float = 0.5, min_turn_rad: float = 0.05) -> float:
    """Effective track width [m] of a skid-steer log: least-squares fit of the wheel distance
    difference (right - left) against the gyro's heading change over ``window_s`` windows.

    The gyro bias is taken from windows where the wheels stand still; windows turning less than
    ``min_turn_rad`` are left out.
    """
    if log.encoders is None or log.gyro is None:
        raise LogFormatError("estimating the track width needs encoders and a gyro")
    left, right = side_distances_m(log.vehicle, log.encoders.ticks)
    start = max(log.encoders.t_s[0], log.gyro.t_s[0]) + 1.0
    stop = min(log.encoders.t_s[-1], log.gyro.t_s[-1]) - 1.0
    grid = np.arange(start, stop, window_s)
    d_right = np.diff(np.interp(grid, log.encoders.t_s, right))
    d_left = np.diff(np.interp(grid, log.encoders.t_s, left))
    d_heading = np.diff(integrate_yaw_rate(log.gyro.t_s, log.gyro.yaw_rate_rad_s, grid))
    still = (np.abs(d_right) + np.abs(d_left)) < 1e-9
    if still.any():
        d_heading = d_heading - np.median(d_heading[still])
    turning = np.abs(d_heading) > min_turn_rad
    if turning.sum() < 10:
        raise LogFormatError("too few turns in the log to estimate the track width")
    return float(np.sum((d_right - d_left)[turning] * d_heading[turning]) / np.sum(d_heading[turning] ** 2))
