"""lidarmap's own drive-log archive (``.drivelog``, a zip); specified in docs/drivelog-format.md.

``manifest.json`` names the format version, the vehicle model, the LiDAR model and the streams;
each stream's columns are ``.npy`` files (``<stream>/<column>.npy``). Reading never extracts to
disk: members are read in memory after checking the entry count, sizes, names (no paths outside
the listed columns) and types (no symlinks). The manifest is validated here with plain Python so
that the engine does not depend on ``api_schemas`` (whose pydantic model describes the same JSON).
"""

from __future__ import annotations

import json
import math
import re
import stat
import zipfile
import zlib
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats._checks import clean_ranges, time_order
from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    LidarModel,
    MotionModelKind,
    OdometryStream,
    ScanStream,
    VehicleModel,
)

FORMAT_NAME = "lidarmap-drivelog"
FORMAT_VERSION = 2  # 2 added the optional scans column angle_offset_rad; files without it are written as 1
MANIFEST = "manifest.json"
MAX_ENTRIES = 64
MAX_MANIFEST_BYTES = 1 << 20
MAX_TOTAL_BYTES = 8 << 30  # uncompressed
# stream kind -> {column: (dtype kind, trailing shape or None for "any", required)}
STREAM_COLUMNS: dict[str, dict[str, tuple[str, tuple[int, ...] | None]]] = {
    "scans": {"t_s": ("f", ()), "ranges_m": ("f", None)},
    "encoders": {"t_s": ("f", ()), "ticks": ("i", None)},
    "gyro": {"t_s": ("f", ()), "yaw_rate_rad_s": ("f", ())},
    "odometry": {"t_s": ("f", ()), "poses": ("f", (3,))},
}
# optional columns: stream kind -> {column: (dtype kind, trailing shape, first format version with it)}
OPTIONAL_COLUMNS: dict[str, dict[str, tuple[str, tuple[int, ...], int]]] = {
    "scans": {"angle_offset_rad": ("f", (), 2)},  # each scan's start angle beyond the lidar's [rad]
}
_MEMBER = re.compile(r"^[a-z_]+/[a-z_]+\.npy$")


def sniff(path: Path) -> bool:
    """A zip whose manifest.json says ``"format": "lidarmap-drivelog"``."""
    if not path.is_file() or not zipfile.is_zipfile(path):
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            info = archive.getinfo(MANIFEST)
            if info.file_size > MAX_MANIFEST_BYTES:
                return False
            return json.loads(archive.read(info)).get("format") == FORMAT_NAME
    except (KeyError, OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, AttributeError):
        return False


# ---------------------------------------------------------------------------------------------- manifest

def _require(condition: bool, message: str, where: str) -> None:
    if not condition:
        raise LogFormatError(message, path=None, location=where)


def _number(value: Any, where: str, positive: bool = False) -> float:
    _require(isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value),
             f"must be a finite number, got {value!r}", where)
    _require(not positive or value > 0, f"must be positive, got {value!r}", where)
    return float(value)


def _optional_number(value: Any, where: str, positive: bool = False) -> float | None:
    return None if value is None else _number(value, where, positive=positive)


def _matrix4(value: Any, where: str) -> np.ndarray:
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        T = None
    if T is None or T.shape != (4, 4) or not bool(np.isfinite(T).all()):
        raise LogFormatError("must be a 4x4 matrix", path=None, location=where)
    _require(np.allclose(T[3], [0, 0, 0, 1]) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6),
             "must be a rigid transform (orthonormal rotation, last row 0 0 0 1)", where)
    return T


def vehicle_from_json(data: Any) -> VehicleModel:
    """VehicleModel from the manifest's ``vehicle`` object (raises LogFormatError naming the field)."""
    _require(isinstance(data, dict), "must be an object", "vehicle")
    kinds = [k.value for k in MotionModelKind]
    _require(data.get("kind") in kinds, f"kind must be one of {kinds}", "vehicle.kind")
    diameters = data.get("wheel_diameters_m")
    if diameters is not None:
        _require(isinstance(diameters, list) and len(diameters) > 0, "must be a list of numbers",
                 "vehicle.wheel_diameters_m")
        diameters = tuple(_number(d, "vehicle.wheel_diameters_m", positive=True) for d in diameters)
    names = data.get("wheel_names", [])
    _require(isinstance(names, list) and all(isinstance(n, str) for n in names), "must be a list of strings",
             "vehicle.wheel_names")
    return VehicleModel(
        kind=MotionModelKind(data["kind"]),
        ticks_per_revolution=_optional_number(data.get("ticks_per_revolution"), "vehicle.ticks_per_revolution",
                                              positive=True),
        wheel_diameters_m=diameters, wheel_names=tuple(names),
        track_width_m=_optional_number(data.get("track_width_m"), "vehicle.track_width_m", positive=True),
        gyro_lowpass_hz=_optional_number(data.get("gyro_lowpass_hz"), "vehicle.gyro_lowpass_hz", positive=True),
        T_vehicle_from_gyro=_matrix4(data.get("T_vehicle_from_gyro", np.eye(4).tolist()),
                                     "vehicle.T_vehicle_from_gyro"),
        name=str(data.get("name", "vehicle")))


def lidar_from_json(data: Any) -> LidarModel | None:
    """LidarModel from the manifest's ``lidar`` object (None when null)."""
    if data is None:
        return None
    _require(isinstance(data, dict), "must be an object or null", "lidar")
    beams = data.get("num_beams")
    _require(isinstance(beams, int) and not isinstance(beams, bool) and beams > 0,
             "must be a positive integer", "lidar.num_beams")
    range_min = _number(data.get("range_min_m"), "lidar.range_min_m")
    range_max = _number(data.get("range_max_m"), "lidar.range_max_m", positive=True)
    _require(0 <= range_min < range_max, "need 0 <= range_min_m < range_max_m", "lidar.range_min_m")
    return LidarModel(num_beams=beams, angle_min_rad=_number(data.get("angle_min_rad"), "lidar.angle_min_rad"),
                      angle_increment_rad=_number(data.get("angle_increment_rad"), "lidar.angle_increment_rad"),
                      range_min_m=range_min, range_max_m=range_max,
                      T_vehicle_from_lidar=_matrix4(data.get("T_vehicle_from_lidar"), "lidar.T_vehicle_from_lidar"),
                      name=str(data.get("name", "lidar")),
                      time_increment_s=_optional_number(data.get("time_increment_s"), "lidar.time_increment_s"))


def validate_manifest(manifest: Any) -> tuple[VehicleModel, LidarModel | None, list[dict]]:
    """Check a parsed manifest; returns (vehicle, lidar, streams). LogFormatError names the field."""
    _require(isinstance(manifest, dict), "manifest must be a JSON object", "manifest")
    _require(manifest.get("format") == FORMAT_NAME, f"format must be {FORMAT_NAME!r}", "format")
    version = manifest.get("format_version")
    _require(isinstance(version, int) and not isinstance(version, bool), "must be an integer", "format_version")
    _require(version <= FORMAT_VERSION, f"version {version} is newer than this reader ({FORMAT_VERSION})",
             "format_version")
    vehicle = vehicle_from_json(manifest.get("vehicle"))
    lidar = lidar_from_json(manifest.get("lidar"))
    streams = manifest.get("streams")
    _require(isinstance(streams, list), "must be a list", "streams")
    seen = set()
    for k, stream in enumerate(streams):
        where = f"streams[{k}]"
        _require(isinstance(stream, dict), "must be an object", where)
        kind = stream.get("kind")
        _require(kind in STREAM_COLUMNS, f"kind must be one of {sorted(STREAM_COLUMNS)}", f"{where}.kind")
        _require(kind not in seen, f"a second {kind} stream", f"{where}.kind")
        seen.add(kind)
        count = stream.get("count")
        _require(isinstance(count, int) and not isinstance(count, bool) and count >= 0,
                 "must be a non-negative integer", f"{where}.count")
        columns = stream.get("columns")
        optional = {c for c, spec in OPTIONAL_COLUMNS.get(kind, {}).items() if spec[2] <= version}
        _require(isinstance(columns, dict) and set(STREAM_COLUMNS[kind]) <= set(columns)
                 and set(columns) <= set(STREAM_COLUMNS[kind]) | optional,
                 f"columns must be exactly {sorted(STREAM_COLUMNS[kind])}"
                 + (f", optionally with {sorted(optional)}" if optional else ""), f"{where}.columns")
        for column, member in columns.items():
            _require(isinstance(member, str) and bool(_MEMBER.match(member)),
                     "member must be '<stream>/<column>.npy' (lower-case letters and _)", f"{where}.columns.{column}")
    _require("scans" not in seen or lidar is not None, "a scans stream needs a lidar model", "lidar")
    return vehicle, lidar, streams


# ---------------------------------------------------------------------------------------------- reading

def _check_archive(archive: zipfile.ZipFile, path: Path, max_total_bytes: int) -> None:
    infos = archive.infolist()
    if len(infos) > MAX_ENTRIES:
        raise LogFormatError(f"archive has {len(infos)} entries (limit {MAX_ENTRIES})", path=str(path))
    total = 0
    for info in infos:
        name = info.filename
        if name.startswith("/") or ".." in name.split("/") or "\\" in name or ":" in name:
            raise LogFormatError(f"unsafe entry name {name!r}", path=str(path))
        if stat.S_ISLNK(info.external_attr >> 16):
            raise LogFormatError(f"entry {name!r} is a symbolic link", path=str(path))
        total += info.file_size
    if total > max_total_bytes:
        raise LogFormatError(f"archive expands to {total} bytes (limit {max_total_bytes})", path=str(path))


def _read_column(archive: zipfile.ZipFile, member: str, path: Path) -> np.ndarray:
    try:
        with archive.open(member) as handle:  # a header declaring more data than the member holds is refused
            version = np.lib.format.read_magic(handle)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            shape, _, dtype = read_header(handle)
            declared = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            held = archive.getinfo(member).file_size - handle.tell()
        if not dtype.hasobject and declared > held:  # (object arrays are refused below: no pickles)
            raise LogFormatError(f"the .npy header declares {declared} bytes of data, the member holds {held}",
                                 path=str(path), location=member)
        with archive.open(member) as handle:
            return np.lib.format.read_array(handle, allow_pickle=False)
    except KeyError:
        raise LogFormatError("column listed in the manifest is missing", path=str(path), location=member) from None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise LogFormatError(f"not a valid .npy array: {error}", path=str(path), location=member) from None


def load(path: Path, max_total_bytes: int = MAX_TOTAL_BYTES) -> DriveLog:
    """Read a .drivelog archive (validated manifest, column shapes and dtypes, time order)."""
    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as error:
        raise LogFormatError(f"not a readable zip archive: {error}", path=str(path)) from None
    with archive:
        _check_archive(archive, path, max_total_bytes)
        try:
            info = archive.getinfo(MANIFEST)
        except KeyError:
            raise LogFormatError("archive has no manifest.json", path=str(path)) from None
        if info.file_size > MAX_MANIFEST_BYTES:
            raise LogFormatError("manifest.json is too large", path=str(path))
        try:
            manifest = json.loads(archive.read(info))
        except (ValueError, UnicodeDecodeError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
            raise LogFormatError(f"manifest.json is not JSON: {error}", path=str(path)) from None
        try:
            vehicle, lidar, streams = validate_manifest(manifest)
        except LogFormatError as error:
            raise LogFormatError(error.message, path=str(path), location=f"manifest.json {error.location}") from None
        warnings: list[str] = []
        built: dict[str, ScanStream | EncoderStream | GyroStream | OdometryStream] = {}
        for stream in streams:
            kind = stream["kind"]
            columns = {c: _read_column(archive, m, path) for c, m in stream["columns"].items()}
            built[kind] = _stream(kind, columns, stream["count"], lidar, vehicle, path, warnings)
    return DriveLog(vehicle=vehicle, lidar=lidar, scans=_built(built, "scans", ScanStream),
                    encoders=_built(built, "encoders", EncoderStream), gyro=_built(built, "gyro", GyroStream),
                    odometry=_built(built, "odometry", OdometryStream), source_format="drivelog",
                    source_path=str(path), warnings=warnings)


_Stream = TypeVar("_Stream", ScanStream, EncoderStream, GyroStream, OdometryStream)


def _built(built: dict[str, ScanStream | EncoderStream | GyroStream | OdometryStream], kind: str,
           cls: type[_Stream]) -> _Stream | None:
    """The stream of ``kind`` that :func:`_stream` built (None when the log has none)."""
    stream = built.get(kind)
    if stream is not None and not isinstance(stream, cls):
        raise TypeError(f"{kind} stream is a {type(stream).__name__}, not a {cls.__name__}")
    return stream


def _stream(kind: str, columns: dict[str, np.ndarray], count: int, lidar: LidarModel | None,
            vehicle: VehicleModel, path: Path,
            warnings: list[str]) -> ScanStream | EncoderStream | GyroStream | OdometryStream:
    specs = {**STREAM_COLUMNS[kind],
             **{c: spec[:2] for c, spec in OPTIONAL_COLUMNS.get(kind, {}).items() if c in columns}}
    for column, (dtype_kind, trailing) in specs.items():
        array = columns[column]
        where = f"{kind}/{column}.npy"
        if array.dtype.kind != dtype_kind:
            raise LogFormatError(f"dtype {array.dtype} is not {'float' if dtype_kind == 'f' else 'integer'}",
                                 path=str(path), location=where)
        if array.ndim == 0 or array.shape[0] != count:
            raise LogFormatError(f"shape {array.shape} does not hold count={count} rows", path=str(path),
                                 location=where)
        if trailing is not None and array.shape[1:] != trailing:
            raise LogFormatError(f"shape {array.shape}, expected ({count}, {', '.join(map(str, trailing))})"
                                 .replace(", )", ")"), path=str(path), location=where)
    t = columns["t_s"].astype(np.float64)
    label = lambda i: f"{kind} row {i}"  # noqa: E731
    order = time_order(t, path, kind, warnings, label)
    if kind == "scans":
        ranges = columns["ranges_m"]
        if lidar is None:  # validate_manifest requires a lidar model for a scans stream
            raise LogFormatError("a scans stream needs a lidar model", path=str(path), location="manifest.json lidar")
        if ranges.ndim != 2 or ranges.shape[1] != lidar.num_beams:
            raise LogFormatError(f"shape {ranges.shape}, expected ({count}, {lidar.num_beams}) beams",
                                 path=str(path), location="scans/ranges_m.npy")
        clean = clean_ranges(ranges, path, "scans", zero_is_no_return=False, location_of=label)
        offsets = columns.get("angle_offset_rad")
        if offsets is not None:
            offsets = offsets.astype(np.float64)
            bad = np.flatnonzero(~(np.abs(offsets) <= 2 * np.pi))
            if bad.size:
                raise LogFormatError(f"angle offset {offsets[bad[0]]:g} rad is not within +-2 pi", path=str(path),
                                     location=f"scans/angle_offset_rad.npy row {int(bad[0])}")
            offsets = offsets[order] if np.any(offsets != 0.0) else None
        return ScanStream(t_s=t[order], ranges_m=clean[order], angle_offset_rad=offsets)
    if kind == "encoders":
        ticks = columns["ticks"]
        wheels = len(vehicle.wheel_names)
        if ticks.ndim != 2 or (wheels and ticks.shape[1] != wheels):
            raise LogFormatError(f"shape {ticks.shape}, expected ({count}, {wheels}) for wheels "
                                 f"{list(vehicle.wheel_names)}", path=str(path), location="encoders/ticks.npy")
        return EncoderStream(t_s=t[order], ticks=ticks.astype(np.int64)[order])
    values = columns["yaw_rate_rad_s" if kind == "gyro" else "poses"].astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(values.reshape(count, -1)).all(axis=1))
    if bad.size:
        raise LogFormatError("value is not finite", path=str(path), location=label(int(bad[0])))
    if kind == "gyro":
        return GyroStream(t_s=t[order], yaw_rate_rad_s=values[order])
    return OdometryStream(t_s=t[order], poses=values[order])


# ---------------------------------------------------------------------------------------------- writing

def vehicle_to_json(vehicle: VehicleModel) -> dict[str, Any]:
    """The manifest's ``vehicle`` object (plain JSON types); :func:`vehicle_from_json` reads it."""
    return {
        "kind": vehicle.kind.value,
        "ticks_per_revolution": vehicle.ticks_per_revolution,
        "wheel_diameters_m": None if vehicle.wheel_diameters_m is None else list(vehicle.wheel_diameters_m),
        "wheel_names": list(vehicle.wheel_names),
        "track_width_m": vehicle.track_width_m,
        "gyro_lowpass_hz": vehicle.gyro_lowpass_hz,
        "T_vehicle_from_gyro": np.asarray(vehicle.T_vehicle_from_gyro, dtype=np.float64).tolist(),
        "name": vehicle.name,
    }


def lidar_to_json(lidar: LidarModel | None) -> dict[str, Any] | None:
    """The manifest's ``lidar`` object (None without a LiDAR); :func:`lidar_from_json` reads it."""
    if lidar is None:
        return None
    return {
        "num_beams": lidar.num_beams, "angle_min_rad": lidar.angle_min_rad,
        "angle_increment_rad": lidar.angle_increment_rad, "range_min_m": lidar.range_min_m,
        "range_max_m": lidar.range_max_m,
        "T_vehicle_from_lidar": np.asarray(lidar.T_vehicle_from_lidar, dtype=np.float64).tolist(),
        "name": lidar.name, "time_increment_s": lidar.time_increment_s,
    }


def manifest_for(log: DriveLog, columns: dict[str, dict[str, str]]) -> dict:
    """The manifest (plain JSON types) describing ``log`` with the given stream columns."""
    counts = log.streams()
    omitted = [name for name in counts if name not in STREAM_COLUMNS]
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION if any(
            c in OPTIONAL_COLUMNS.get(kind, {}) for kind, cols in columns.items() for c in cols) else 1,
        "vehicle": vehicle_to_json(log.vehicle),
        "lidar": lidar_to_json(log.lidar),
        "streams": [{"kind": kind, "count": counts[kind], "columns": cols} for kind, cols in columns.items()],
        "omitted_streams": omitted,
        "source": {"format": log.source_format, "path": log.source_path},
    }


def write(log: DriveLog, out_dir: Path, name: str = "log") -> Path:
    """Write ``out_dir/<name>.drivelog``. Camera streams are not stored (listed as omitted)."""
    path = Path(out_dir) / f"{name}.drivelog"
    arrays: dict[str, dict[str, np.ndarray]] = {}
    if log.scans is not None:
        arrays["scans"] = {"t_s": log.scans.t_s, "ranges_m": np.asarray(log.scans.ranges_m, dtype=np.float32)}
        if log.scans.angle_offset_rad is not None:
            arrays["scans"]["angle_offset_rad"] = np.asarray(log.scans.angle_offset_rad, dtype=np.float64)
    if log.encoders is not None:
        arrays["encoders"] = {"t_s": log.encoders.t_s, "ticks": np.asarray(log.encoders.ticks, dtype=np.int64)}
    if log.gyro is not None:
        arrays["gyro"] = {"t_s": log.gyro.t_s, "yaw_rate_rad_s": log.gyro.yaw_rate_rad_s}
    if log.odometry is not None:
        arrays["odometry"] = {"t_s": log.odometry.t_s, "poses": log.odometry.poses}
    columns = {kind: {col: f"{kind}/{col}.npy" for col in cols} for kind, cols in arrays.items()}
    manifest = manifest_for(log, columns)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as archive:
        archive.writestr(MANIFEST, json.dumps(manifest, indent=2))
        for kind, cols in arrays.items():
            for col, array in cols.items():
                with archive.open(columns[kind][col], "w", force_zip64=True) as handle:
                    np.lib.format.write_array(handle, np.ascontiguousarray(array), allow_pickle=False)
    return path
